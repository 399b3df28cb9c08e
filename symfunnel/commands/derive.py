"""`symfunnel derive [SCENARIO] [--json] [--eval POINT.json] [--latex FILE]`: the design's signals with their sizes
and free variables, their values at points, or a LaTeX document of them."""

from __future__ import annotations

from ..core.errors import InputError
from ._common import LOADING, _dump, _load, loading

#: the steps of `derive`, in order; each phase runs under one of them (deadline.step), so a wall-clock limit reached
#: anywhere in the command names what it was doing
DERIVING = "deriving the design"             # Run.design's step
EVALUATING = "evaluating the signals at the points"
COUNTING = "counting the signals' operations and free variables"
WRITING = "writing the LaTeX"
STEPS = (LOADING, DERIVING, EVALUATING, COUNTING, WRITING)


def register(sub, common) -> None:
    """Add the `derive` subcommand."""
    sp = sub.add_parser("derive", help="build the design; print each signal's size and free variables")
    common(sp)
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.add_argument("--eval", metavar="POINT.json", help="evaluate every signal at a point (or a list)")
    sp.add_argument("--latex", metavar="FILE", help="write the signals as LaTeX")
    sp.add_argument("--all", action="store_true", help="with --eval: also print Phi and the ESN/adaptation rates")
    from ._common import add_force_option
    add_force_option(sp)
    sp.set_defaults(func=cmd_derive)


def _read_points(path: str):
    from ..core.inputs import loads_json, read_text
    expected = '{"t": ..., "q": [...], "dq": [...]} or a list of such objects'
    data = loads_json(read_text(path, expected="a JSON point file"), file=path, expected=expected)
    return data


def cmd_derive(args) -> int:
    """`symfunnel derive`: signals with size and free variables; --eval values at points; --latex formulas."""
    from ..core import deadline
    if args.latex:
        from ..core.outputs import check_output_file
        check_output_file(args.latex, key="--latex")
    with loading():
        from ..design import evaluate
        from ..core.names import compress_names
        from ..pipeline import Run
        sc = _load(args)
    if args.latex:
        from ..core.outputs import check_replaceable
        from ._common import scenario_inputs
        check_replaceable(args.latex, key="--latex", inputs=scenario_inputs(sc), force=args.force)
    d = Run(sc).design                  # under its own step, DERIVING
    if args.eval:
        with deadline.step(EVALUATING):
            data = _read_points(args.eval)
            if isinstance(data, list):
                if not data:
                    raise InputError("is an empty list", file=args.eval, expected="at least one point")
                values = [evaluate(d, p, file=args.eval, key=f"[{i}]") for i, p in enumerate(data)]
            else:
                values = evaluate(d, data, file=args.eval)
        if args.json:
            print(_dump({"values": values}))
        else:
            for i, vals in enumerate(values if isinstance(values, list) else [values]):
                if isinstance(values, list):
                    print(f"# point {i}")
                for k, v in vals.items():
                    if (k == "Phi" or k.endswith("_dot") and k[:-4] in dict(d.states)) and not args.all:
                        continue
                    print(f"{k:>11} = {_short(v)}")
        return 0
    names = list(d.signal_info)
    info = {}
    with deadline.step(COUNTING):       # tens of seconds for a large reservoir
        for k in names:
            info[k] = {"ops": d.ops(k), "free": d.free_symbols(k), "shape": list(d.signals[k].shape)}
    if args.latex:
        with deadline.step(WRITING):
            _write_latex(d, names, args.latex)
    if args.json:
        print(_dump({"scenario": sc.name, "signals": info}))
        return 0
    print(f"scenario {sc.name}: {sc.title}")
    print(f"  model {sc.model.kind}, n = {sc.n}, C {sc.model.C_source}; design {sc.design.variant}, transform "
          f"{sc.design.transform}, approximator {sc.design.approximator}"
          + (f" (N = {sc.esn.size})" if sc.design.approximator == "esn" else ""))
    print(f"{'signal':>11} {'shape':>7} {'ops':>6}  free variables")
    for k in names:
        i = info[k]
        free = compress_names(i["free"])
        print(f"{k:>11} {i['shape'][0]:>3}x{i['shape'][1]:<3} {i['ops']:>6}  {free}")
    if args.latex:
        print(f"LaTeX written to {args.latex}")
    return 0


def _short(v) -> str:
    import numpy as np
    if v is None:
        return "null (outside its funnel)"
    a = np.array(v, dtype=float)
    return np.array2string(a, precision=8, max_line_width=200, threshold=20)


def _write_latex(d, names, path) -> None:
    """A compilable LaTeX document (article + amsmath): each signal small enough to read as a displayed
    equation (converted from SX), the operation count for the rest."""
    import sympy

    from ..core.io import atomic_write
    from ..sx.tosympy import sx_to_sympy
    name = _tex_text(d.scenario.name)
    body = []
    for k in names:
        f = d.function(k)
        ops = d.ops(k)
        head = f"\\paragraph{{${_tex_name(k)}$ (\\texttt{{{_tex_text(k)}}}, {ops} operations)}}"
        if ops <= 400 and k not in ("Phi",):
            m = sx_to_sympy(d.signals[k], [d.sym[x] for x in d.inputs_of(k)])
            tex = sympy.latex(m[0] if m.shape == (1, 1) else m, mat_delim="[")
            body += [head, "\\begin{equation*}", f"{_tex_name(k)} = {tex}", "\\end{equation*}", ""]
        else:
            body += [head, f"Too large to print ({f.n_instructions()} tape instructions).", ""]
    lines = [f"% symfunnel derive --latex: scenario {d.scenario.name}",
             "\\documentclass[10pt]{article}",
             "\\usepackage[a4paper,landscape,margin=1.5cm]{geometry}",
             "\\usepackage{amsmath}",
             "\\setcounter{MaxMatrixCols}{200}",
             "\\allowdisplaybreaks",
             "\\begin{document}",
             f"\\section*{{Signals of scenario \\texttt{{{name}}}}}",
             "Derived by symfunnel (CasADi SX, converted to sympy). Long expressions may run past the margin.",
             "", *body, "\\end{document}", ""]
    from ..core.lifecycle import committing
    with committing():          # the command's one file, written: from here on it has succeeded (the text is built
        atomic_write(path, "\n".join(lines))    # before: a signal while building it stops the command)


def _tex_text(s: str) -> str:
    """Escape plain text for LaTeX."""
    table = {"\\": r"\textbackslash{}", "{": r"\{", "}": r"\}", "_": r"\_", "%": r"\%", "$": r"\$",
             "#": r"\#", "&": r"\&", "^": r"\^{}", "~": r"\~{}"}
    return "".join(table.get(c, c) for c in s)


def _tex_name(k: str) -> str:
    table = {"alpha2": r"\alpha_2", "alpha2_dot": r"\dot\alpha_2", "zeta1": r"\zeta_1", "zeta2": r"\zeta_2",
             "mu1": r"\mu_1", "mu2": r"\mu_2", "z1_dot": r"\dot z_1", "z2_dot": r"\dot z_2", "tau": r"\tau",
             "Phi": r"\Phi", "w_hat_dot": r"\dot{\hat W}", "x_esn_dot": r"\dot x_{esn}"}
    if k in table:
        return table[k]
    return r"\mathrm{" + k.replace("_", r"\_") + "}" if "_" in k else k
