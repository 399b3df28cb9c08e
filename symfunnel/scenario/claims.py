"""What a scenario declares about its source: the printed claims the audit checks, the expected outcomes of other
checks (`[[expect]]`) and the deviations from the source."""

from __future__ import annotations

from typing import Any

from ..core import validate as V
from ..core.errors import InputError
from ..core.names import CONSTANTS, EXPECT_STATUSES, IDENT, SIGNALS, check_ids
from ..expr import Expression, parse_expression
from .document import Claim, Deviation, Expectation
from .sections import parse_funnel_table


def claim_names(n: int, model) -> set[str]:
    """Every name a claim expression may use: time, coordinates, parameters, signals and design constants."""
    names = {"t", "x_esn", "w_hat", "q", "dq"} | set(SIGNALS) | set(CONSTANTS)
    names |= set(model.coordinates) | {"d" + c for c in model.coordinates} | set(model.p_names)
    return names


def expression_pair(c: dict, p: str, keys: tuple[str, str], exclusive: tuple[str, ...], kind: str, whose: str,
                     names: set[str], file: str) -> tuple[Expression, Expression]:
    """The two expressions of a claim kind given by a pair of keys (lhs/rhs, rho/delta), alone of their kind."""
    a, b = keys
    for k in exclusive:
        if k in c:
            raise InputError(f"cannot be combined with '{a}'/'{b}'", file=file, key=f"{p}.{k}",
                             expected=f"{kind} has {a} and {b} only")
    for k in keys:
        if k not in c:
            raise InputError("is missing", file=file, key=f"{p}.{k}", expected=f"{a} and {b} {whose}")
    return tuple(parse_expression(V.get_str(c, k, file=file, prefix=p), names, file=file, key=f"{p}.{k}")
                 for k in keys)


#: what an inequality claim may name besides a signal claim's names: the design's V and its exact derivative along
#: the nominal model plus W*^T Phi (eps = 0: the ideal approximation such printed steps assume), and W*
INEQUALITY_NAMES = {"V", "V_dot", "W_star"}


def parse_claims(items: Any, n: int, file: str, model, funnels) -> list[Claim]:
    if not isinstance(items, list):
        raise InputError(f"is {V.a_type(items)}", file=file, key="claims",
                         expected="an array of tables ([[claims]])")
    names = claim_names(n, model)
    seen = set()
    out = []
    for i, c in enumerate(items):
        p = f"claims[{i}]"
        V.check_keys(c, ["name", "source", "description", "signal", "expression", "funnel", "phi0",
                         "phi_inf", "a", "rho", "delta", "lhs", "rhs", "expect", "parameters"], file=file, prefix=p,
                     required=["name"])
        name = V.get_str(c, "name", file=file, prefix=p)
        if not IDENT.match(name) or len(name) > 64:
            raise InputError(f"is '{name}'", file=file, key=p + ".name", expected="an identifier")
        if name in seen:
            raise InputError(f"'{name}' is used twice", file=file, key=p + ".name", expected="unique claim names")
        seen.add(name)
        source = V.get_str(c, "source", "", file=file, prefix=p)
        desc = V.get_str(c, "description", "", file=file, prefix=p)
        expect = V.get_str(c, "expect", "pass", file=file, prefix=p, choices=list(EXPECT_STATUSES))
        params_raw = c.get("parameters", {})
        V.check_keys(params_raw, list(params_raw) if isinstance(params_raw, dict) else [], file=file,
                     prefix=p + ".parameters")
        params = {}
        for k, v in params_raw.items():
            if not IDENT.match(k) or k in names:
                raise InputError(f"'{k}' is not a new identifier", file=file, key=f"{p}.parameters.{k}",
                                 expected="a name the claim's expression uses that is not a signal, symbol or parameter")
            params[k] = V.as_float(v, file=file, key=f"{p}.parameters.{k}")
        cnames = names | set(params)
        if "lhs" in c or "rhs" in c:
            lhs, rhs = expression_pair(c, p, ("lhs", "rhs"), ("signal", "expression", "funnel", "rho", "delta"),
                                        "an inequality claim", "of the inequality", cnames | INEQUALITY_NAMES, file)
            out.append(Claim(name, source, desc, "inequality", lhs=lhs, rhs=rhs, expect=expect, parameters=params))
            continue
        if "rho" in c or "delta" in c:
            rho, delta = expression_pair(c, p, ("rho", "delta"), ("signal", "expression", "funnel"),
                                          "a decay claim", "of the claim", names | {"W_star_norm2"}, file)
            out.append(Claim(name, source, desc, "decay", rho=rho, delta=delta, expect=expect))
            continue
        if "funnel" in c:
            for k in ("signal", "expression"):
                if k in c:
                    raise InputError("cannot be combined with 'funnel'", file=file, key=f"{p}.{k}",
                                     expected="either funnel + phi0/phi_inf/a, or signal + expression")
            fn = V.get_str(c, "funnel", file=file, prefix=p, choices=["e1", "e2"])
            base = funnels[fn]
            inherit = (base.phi0, base.phi_inf, base.a) if hasattr(base, "phi0") else None
            spec = parse_funnel_table({k: c[k] for k in ("phi0", "phi_inf", "a") if k in c}, n, file, p, inherit)
            out.append(Claim(name, source, desc, "funnel", funnel=fn, spec=spec, expect=expect))
            continue
        for k in ("phi0", "phi_inf", "a"):
            if k in c:
                raise InputError("is only allowed with 'funnel'", file=file, key=f"{p}.{k}",
                                 expected="signal + expression for an equation claim")
        if "signal" not in c or "expression" not in c:
            missing = "signal" if "signal" not in c else "expression"
            raise InputError("is missing", file=file, key=f"{p}.{missing}",
                             expected="signal + expression, or funnel + phi0/phi_inf/a")
        sig = V.get_str(c, "signal", file=file, prefix=p, choices=sorted(SIGNALS))
        expr = parse_expression(V.get_str(c, "expression", file=file, prefix=p), cnames, file=file,
                                key=p + ".expression")
        out.append(Claim(name, source, desc, "signal", signal=sig, expression=expr, expect=expect, parameters=params))
    return out


def parse_expectations(items: Any, n: int, claims: list[Claim], file: str) -> list[Expectation]:
    """`[[expect]]`: declared outcomes of non-claim checks, each naming a known check id and giving a reason."""
    if not isinstance(items, list):
        raise InputError(f"is {V.a_type(items)}", file=file, key="expect",
                         expected="an array of tables ([[expect]])")
    known = check_ids(n)
    out, seen = [], set()
    for i, e in enumerate(items):
        p = f"expect[{i}]"
        V.check_keys(e, ["check", "status", "reason"], file=file, prefix=p, required=["check", "status", "reason"])
        cid = V.get_str(e, "check", file=file, prefix=p)
        if cid.startswith("claim."):
            raise InputError(f"is '{cid}'", file=file, key=p + ".check",
                             expected="a non-claim check id (a claim declares its outcome with `expect`)")
        if cid not in known:
            raise InputError(f"is '{cid}', not a check id{V.did_you_mean(cid, known)}", file=file, key=p + ".check",
                             expected="a check id of audit or verify (see docs/scenario.md)")
        if cid in seen:
            raise InputError(f"'{cid}' is declared twice", file=file, key=p + ".check", expected="one entry per check")
        seen.add(cid)
        status = V.get_str(e, "status", file=file, prefix=p, choices=list(EXPECT_STATUSES))
        reason = V.get_str(e, "reason", file=file, prefix=p).strip()
        from ..core.text import invisible
        if not any(not invisible(c) and not c.isspace() for c in reason):
            raise InputError("is empty", file=file, key=p + ".reason", expected="why the outcome is expected")
        out.append(Expectation(cid, status, reason))
    return out


def parse_deviations(items: Any, file: str) -> list[Deviation]:
    if not isinstance(items, list):
        raise InputError(f"is {V.a_type(items)}", file=file, key="deviations",
                         expected="an array of tables ([[deviations]])")
    out = []
    for i, d in enumerate(items):
        p = f"deviations[{i}]"
        V.check_keys(d, ["key", "paper", "value", "reason"], file=file, prefix=p, required=["key", "reason"])
        out.append(Deviation(V.get_str(d, "key", file=file, prefix=p), V.get_str(d, "paper", "", file=file, prefix=p),
                             V.get_str(d, "value", "", file=file, prefix=p), V.get_str(d, "reason", file=file, prefix=p)))
    return out
