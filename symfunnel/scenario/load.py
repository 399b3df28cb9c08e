"""A built-in name or a TOML path to a validated `Scenario`: reading the file and validating the document section by
section."""

from __future__ import annotations

import re
from pathlib import Path

from ..core import validate as V
from ..core.errors import InputError
from ..family.approximators import parse_rbf
from ..family.funnels import check_positive
from ..family.projection import DEFAULT_LAYER as PROJECTION_LAYER
from ..plant.nonlinearities import check_smoothing_width
from .claims import parse_claims, parse_deviations, parse_expectations
from .document import Scenario
from .sections import (
    build_model,
    check_reference,
    check_settings_match,
    parse_audit,
    parse_design,
    parse_esn,
    parse_funnel_table,
    parse_initial,
    parse_plant,
    parse_reference,
    parse_simulation,
    parse_x_esn0,
)

DATA_DIR = Path(__file__).resolve().parent.parent / "data"

BUILTIN = {"paper": "paper_2dof.toml", "arm7": "arm7.toml"}

TOP_KEYS = ["name", "title", "description", "source", "deviations", "model", "reference", "initial",
            "funnel", "controller", "adaptation", "esn", "plant", "simulation", "audit", "claims", "design",
            "approximator", "expect", "uncertainty", "sweep", "implementation", "rbf", "tune"]


def resolve(name_or_path: str | Path | None) -> Path:
    """A built-in scenario name or a path to a TOML file -> the file's path (InputError if neither)."""
    if name_or_path is None:
        name_or_path = "paper"
    s = str(name_or_path)
    p = Path(s)
    if p.exists():
        if p.is_dir():
            raise InputError("is a directory", file=s, expected="a scenario TOML file or a built-in name")
        return p
    if s in BUILTIN:
        return DATA_DIR / BUILTIN[s]
    hint = V.did_you_mean(s, BUILTIN)
    raise InputError(f"no such file or built-in scenario{hint}", file=s,
                     expected="a path to a .toml file or one of " + ", ".join(BUILTIN))


def is_builtin(path: str | Path) -> bool:
    """Whether `path` is one of the scenario files shipped with symfunnel."""
    try:
        p = Path(path).resolve()
    except OSError:
        return False
    return any(p == (DATA_DIR / f).resolve() for f in BUILTIN.values())


def load_scenario(name_or_path: str | Path | None = None) -> Scenario:
    """Load and validate a scenario (a path or a built-in name such as 'paper')."""
    path = resolve(name_or_path)
    file = str(path)
    from ..core.inputs import loads_toml, read_text
    from ..core.inputs import recording
    with recording() as seen:
        text = read_text(path, expected="a scenario TOML file")
        raw = loads_toml(text, file=file)
        default_name = path.stem if str(name_or_path) not in BUILTIN else str(name_or_path)
        sc = from_dict(raw, file=file, base_dir=path.parent, default_name=default_name)
    sc.inputs.update(seen)
    return sc


def from_dict(raw: dict, *, file: str, base_dir: Path, default_name: str = "scenario") -> Scenario:
    """Validate a parsed TOML document into a Scenario; `Scenario.inputs` names every other file it read, with
    the sha256 of the content read (a campaign's fingerprint covers them)."""
    from ..core.inputs import recording
    with recording() as seen:
        sc = _from_dict(raw, file=file, base_dir=base_dir, default_name=default_name)
    sc.inputs.update(seen)
    return sc


def _from_dict(raw: dict, *, file: str, base_dir: Path, default_name: str) -> Scenario:
    V.check_keys(raw, TOP_KEYS, file=file, prefix="", required=["model", "reference", "initial"])
    name = V.get_str(raw, "name", default_name, file=file, prefix="")
    if not re.match(r"^[A-Za-z0-9_.-]{1,64}$", name):
        raise InputError(f"is '{name}'", file=file, key="name",
                         expected="1-64 characters of letters, digits, '_', '-', '.'")
    title = V.get_str(raw, "title", name, file=file, prefix="")
    description = V.get_str(raw, "description", "", file=file, prefix="")
    source = V.get_str(raw, "source", "", file=file, prefix="")
    deviations = parse_deviations(raw.get("deviations", []), file)

    model = build_model(raw["model"], file=file, base_dir=base_dir)
    n = model.n

    reference = parse_reference(raw["reference"], n, file, model)
    q0, dq0, init = parse_initial(raw["initial"], n, file)

    funnel_raw = raw.get("funnel", {})
    V.check_keys(funnel_raw, ["e1", "e2"], file=file, prefix="funnel")
    funnels = {
        "e1": parse_funnel_table(funnel_raw.get("e1", {}), n, file, "funnel.e1", (0.5, 0.02, 1.0), model.parameter_dict()),
        "e2": parse_funnel_table(funnel_raw.get("e2", {}), n, file, "funnel.e2", (2.0, 0.1, 1.0), model.parameter_dict()),
    }

    ctl = raw.get("controller", {})
    V.check_keys(ctl, ["k1", "k2"], file=file, prefix="controller")
    k1 = V.per_joint(ctl, "k1", n, 5.0, file=file, prefix="controller", minimum=0, strict_min=True)
    k2 = V.per_joint(ctl, "k2", n, 10.0, file=file, prefix="controller", minimum=0, strict_min=True)

    ad = raw.get("adaptation", {})
    V.check_keys(ad, ["gamma", "sigma", "w_hat0", "projection", "projection_layer"], file=file, prefix="adaptation")
    gamma = V.get_float(ad, "gamma", 10.0, file=file, prefix="adaptation", minimum=0, strict_min=True)
    sigma = V.get_float(ad, "sigma", 0.02, file=file, prefix="adaptation", minimum=0)
    w_hat0 = V.get_float(ad, "w_hat0", 0.0, file=file, prefix="adaptation")
    projection = (V.get_float(ad, "projection", file=file, prefix="adaptation", minimum=0, strict_min=True)
                  if "projection" in ad else None)
    projection_layer = V.get_float(ad, "projection_layer", PROJECTION_LAYER, file=file, prefix="adaptation", minimum=0,
                                   maximum=1, strict_min=True)
    if "w_hat" in init:
        w_hat0 = V.as_float(init["w_hat"], file=file, key="initial.w_hat")

    esn = parse_esn(raw.get("esn", {}), file)
    x_esn0 = parse_x_esn0(init, esn.size, file)
    plant = parse_plant(raw.get("plant", {}), n, file, model, base_dir)
    sim = parse_simulation(raw.get("simulation", {}), file)
    check_smoothing_width(sim.smoothing_width, plant, file=file, key="simulation.smoothing_width")
    for i, w in enumerate(sim.convergence_widths):
        check_smoothing_width(w, plant, file=file, key=f"simulation.convergence_widths[{i}]")
    check_reference(reference, sim.t_final, file)
    for key, shape in funnels.items():
        check_positive(shape, sim.t_final, file=file, key=f"funnel.{key}" + (".F" if "F" in shape.KEYS else ""))
    audit = parse_audit(raw.get("audit", {}), n, file, model)
    if model.kind == "matrices":
        from ..model.matrices_check import check_inertia_matrix
        check_inertia_matrix(model, q0, audit.joint_lower, audit.joint_upper, file=file)
    claims = parse_claims(raw.get("claims", []), n, file, model, funnels)
    design = parse_design(raw.get("design", {}), raw.get("approximator", {}), file)
    check_settings_match(raw, design.approximator, file)
    rbf = None
    if design.approximator == "rbf":
        rbf = parse_rbf(raw.get("rbf", {}), n, file=file, joint_lower=audit.joint_lower,
                        joint_upper=audit.joint_upper, velocity_range=audit.velocity_range)
    expectations = parse_expectations(raw.get("expect", []), n, claims, file)
    from .uncertainty import parse_campaign
    campaign = parse_campaign(raw, file=file, n=n, model=model, plant=plant)
    if campaign is not None and campaign.sweep.t_final is not None:
        V.check_horizon(campaign.sweep.t_final, sim.dt, key="sweep.t_final", file=file)
    # regularity proven by interval arithmetic over the longest horizon the scenario runs (after the grid checks,
    # which name a time for the common mistakes)
    from .regularity import check_funnel_regular, check_reference_regular
    horizon = max(sim.t_final, (campaign.sweep.t_final or 0.0) if campaign is not None else 0.0)
    check_reference_regular(reference, horizon, file=file)
    for key, shape in funnels.items():
        check_funnel_regular(shape, horizon, file=file,
                             key=f"funnel.{key}" + (".F" if "F" in shape.KEYS else ""))
    impl = None
    if "implementation" in raw:
        from .implementation import parse_implementation
        impl = parse_implementation(raw["implementation"], n=n, file=file, raw_model=raw["model"], base_dir=base_dir)
    tune = None
    if "tune" in raw:
        from .tune import parse_tune
        tune = parse_tune(raw["tune"], file=file, has_implementation=impl is not None, funnels=funnels, n=n,
                          raw_model=raw["model"], base_dir=base_dir)

    return Scenario(name=name, path=Path(file), title=title, description=description, source=source,
                    deviations=deviations, model=model, reference=reference, q0=q0, dq0=dq0,
                    x_esn0=x_esn0, w_hat0=w_hat0, funnels=funnels, k1=k1, k2=k2, gamma=gamma,
                    sigma=sigma, esn=esn, plant=plant, simulation=sim, audit=audit, claims=claims,
                    design=design, expectations=expectations, raw=raw, campaign=campaign, implementation=impl,
                    rbf=rbf, tune=tune, projection=projection, projection_layer=projection_layer)


def replace(self: Scenario, changes: dict | None = None, /, **kw) -> Scenario:
    """A new Scenario with the scenario-file keys changed (dotted keys, `__` for the dot in keyword form:
    `replace(controller__k2=[1, 1])`, `replace({"funnel.e2.phi0": 0.5})`; None removes a key), validated like the
    loader (InputError naming the key otherwise); this one is unchanged."""
    import copy
    raw = copy.deepcopy(self.raw)
    items = dict(changes or {})
    items.update({k.replace("__", "."): v for k, v in kw.items()})
    for key, value in items.items():
        *path, leaf = key.split(".")
        t = raw
        for p in path:
            nxt = t.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise InputError(f"is not a table, so '{key}' cannot be set", file=self.file, key=p,
                                 expected="a dotted key of the scenario file")
            t = nxt
        if value is None:
            t.pop(leaf, None)
        else:
            t[leaf] = value
    return from_dict(raw, file=self.file, base_dir=self.path.parent, default_name=self.name)


Scenario.replace = replace      # the method lives here: the loader's validation is what it needs
