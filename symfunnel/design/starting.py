"""Starting scenarios a user edits (what `symfunnel init` writes): a 2-link planar arm under gravity, a URDF's
movable joints (a reference that swings each joint gently around the middle of its range, an initial state a little
off it, funnels that contain the initial errors, e2's initial width from the derived e2(0) with a factor 2 to spare),
or a copy of a built-in or a file."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

#: e1(0): every joint starts this far from the reference (rad, or m for prismatic joints).
OFFSET = 0.02
#: The reference swings each joint by at most this much around its home position (rad; prismatic: m).
SWING, SWING_PRISMATIC = 0.2, 0.05


def write_starting(out, *, urdf: str | None = None, source: str | None = None, joints=None, force: bool = False,
                   say=None) -> Path:
    """Write a starting scenario to `out` (.toml): a copy of `source` (a built-in name or a file, with the robot
    file it names), the joints of `urdf` (`joints` a comma-separated string or a list of names: a subset), else a
    2-link planar arm; refuses an existing file unless `force`, and an input as the output. Errors name the CLI's
    options (the API renames them)."""
    from ..core.errors import InputError
    from ..core.io import atomic_write
    from ..core.outputs import check_not_input, check_output_file
    out = Path(out)
    if out.suffix != ".toml":
        raise InputError(f"is '{out}'", key="--out", expected="a file name ending in .toml")
    check_output_file(out)
    check_not_input(out, [Path(p) for p in (source, urdf) if p and Path(p).is_file()], key="--out")
    if out.exists() and not force:
        raise InputError("exists", file=str(out), key="--out", expected="a new file (or --force to overwrite it)")
    if source and urdf:
        raise InputError("is given with --urdf", key="--from", expected="either --from or --urdf")
    if joints and not urdf:
        raise InputError("is given without --urdf", key="--joints", expected="--urdf FILE --joints NAMES")
    if source:
        text, extra = copied_scenario(source, out)
        for path, data in extra:
            if not path.exists():                   # else the same robot (copied_scenario refuses another)
                atomic_write(path, data)
        atomic_write(out, text)
        return out
    name = _name(out.stem)
    if isinstance(joints, str):
        joints = [j.strip() for j in joints.split(",") if j.strip()] or None
    text = (scenario_from_urdf(urdf, out, name, joints=list(joints) if joints else None, say=say) if urdf
            else scenario_two_link(name, out))
    atomic_write(out, text)
    return out


def copied_scenario(source: str, out: Path) -> tuple[str, list[tuple[Path, str]]]:
    """The text of a built-in scenario or a file, with a header naming where it came from, and the files it refers
    to by a relative path (a URDF) to write beside `out`: (text, [(path, contents)])."""
    import datetime
    import tomllib

    from ..core.errors import InputError
    from ..core.inputs import read_text
    from ..scenario import BUILTIN, DATA_DIR, load_scenario
    sc = load_scenario(source)              # validates it: a copy that does not load is never written
    src = DATA_DIR / BUILTIN[source] if source in BUILTIN else Path(source)
    text = read_text(src, expected="a scenario TOML file")
    extra = []
    path = (tomllib.loads(text).get("model") or {}).get("path")
    if isinstance(path, str) and not Path(path).is_absolute():
        ref = src.parent / path
        if not ref.is_file():
            raise InputError("is not a file", file=str(ref), key="model.path", expected="the URDF the scenario uses")
        # the copy goes next to the output, never above it (a '../' path), and never onto another robot's file
        copy = out.parent / Path(path).name
        data = ref.read_text(encoding="utf-8")
        if copy.exists() and not _same_text(copy, data):
            raise InputError(f"exists with other content than the scenario's robot {ref}", file=str(copy),
                             key="model.path", expected="a directory for --out without a different file of that name")
        if Path(path).name != path:
            text = _repoint(text, path, Path(path).name)
        extra.append((copy, data))
    mjcf = ((tomllib.loads(text).get("plant") or {}).get("mujoco") or {}).get("mjcf")
    if isinstance(mjcf, str) and not Path(mjcf).is_absolute():
        # an MJCF may include files and meshes relative to itself: the copy names it where it is, not a copy of it
        text = _repoint(text, mjcf, str((src.parent / mjcf).resolve()), key="mjcf", why="the MJCF of")
    origin = f"the built-in scenario '{source}'" if source in BUILTIN else f"{_toml_text(str(src))}"
    day = datetime.date.today().isoformat()
    head = (f"# Copied by `symfunnel init --from {_toml_text(source)}` from {origin} ({sc.name}) on {day}.\n"
            "# Edit it freely (docs/scenario.md lists every key). If you change the design it describes, a printed\n"
            "# claim ([[claims]]) that no longer matches fails the gate: remove it or declare expect = \"fail\".\n")
    return head + text, extra


def _same_text(path: Path, data: str) -> bool:
    try:
        return path.read_bytes() == data.encode("utf-8")
    except OSError:
        return False


def _repoint(text: str, old: str, new: str, *, key: str = "path", why: str = "copied beside this file from") -> str:
    """The scenario text with its `key = old` rewritten to new (the copy beside it, or the original's full path)."""
    import re
    import tomllib
    lines = text.split("\n")
    for i, line in enumerate(lines):
        if re.match(rf"\s*{key}\s*=", line):
            try:
                value = tomllib.loads(line)[key]
            except (tomllib.TOMLDecodeError, KeyError):
                continue
            if value == old:
                lines[i] = f'{key} = "{_toml_text(new)}"' + f"          # {why} " + _toml_text(old)
                return "\n".join(lines)
    return text


def _name(stem: str) -> str:
    """A valid scenario name from a file stem."""
    import re
    s = re.sub(r"[^A-Za-z0-9_.-]", "_", stem)[:64]
    return s or "scenario"


def scenario_two_link(name: str, out: Path) -> str:
    """A planar 2-link arm under gravity, with friction, a dead zone and a 10 % mass error in the plant."""
    return f'''# A scenario written by `symfunnel init`: a planar 2-link arm under gravity. Every key is described in
# docs/scenario.md. Units are SI: lengths in m, masses in kg, angles in rad, time in s, torques in N m.
# Try: symfunnel derive {_toml_text(str(out))}; symfunnel audit ...; symfunnel simulate ...
# What `symfunnel verify` checks: the model (symmetry, Property 1), the funnels at t = 0, a simulated run (both
# funnels kept, Lyapunov decay, bounded signals) and the interval certificates (input gain, containment, bounds).
# It exits 1 only on an outcome this file does not declare; warnings (an undecided certificate, a vacuous Lyapunov
# level-set argument) never fail it. To declare a finding you expect, e.g. a refuted input-gain assumption:
#   [[expect]]
#   check = "certify.input_gain"
#   status = "fail"
#   reason = "why this design is expected to fail it"
# status = "pass" instead makes a check required (certify.invariance: the Lyapunov argument must close).
name = "{name}"
title = "Funnel control of a planar 2-link arm (symfunnel init)"

[model]
type = "planar"                   # joints revolute about z, links in the x-y plane
gravity = [0.0, -9.81, 0.0]       # m/s^2, in the base frame
links = [
    {{ mass = 1.0, length = 0.5 }},   # kg, m; centre of mass at length/2, inertia mass*length^2/12 (defaults)
    {{ mass = 0.8, length = 0.4 }},
]

[reference]
q = ["0.3*sin(t)", "0.2*sin(1.5*t)"]   # q_d(t) in rad; dq_d and ddq_d are derived symbolically

[initial]
q = [{OFFSET}, -{OFFSET}]               # rad: a little off the reference, so the funnels have work to do
dq = 0.0                          # rad/s

[funnel.e1]                       # F1(t) = phi0 exp(-a t) + phi_inf, in rad; must contain |e1(0)| = {OFFSET}
phi0 = 0.2
phi_inf = 0.01
a = 1.0                           # 1/s

[funnel.e2]                       # F2(t) for the velocity-level error e2 = dq - alpha2, in rad/s
phi0 = 2.0
phi_inf = 0.1
a = 1.0

[controller]
k1 = 5.0                          # gain of the virtual control alpha2
k2 = 10.0                         # gain of the torque loop

[adaptation]
gamma = 10.0                      # Gamma = gamma I
sigma = 0.02                      # sigma-modification (leakage)

[esn]                             # echo state network that learns what the model does not know
size = 30
seed = 1

[plant]                           # the simulated arm: what the controller does not know
viscous = 0.5                     # N m s/rad
coulomb = 0.2                     # N m
mass_scale = 1.1                  # the true arm is 10 % heavier than the model

[plant.dead_zone]                 # actuator dead zone: no torque between b_l and b_r, N m
b_l = -0.3
b_r = 0.3

[simulation]
t_final = 10.0                    # s
dt = 0.01                         # s, output grid
'''


def _fmt(x: float) -> str:
    return repr(round(float(x), 6))


def scenario_from_urdf(urdf: str, out: Path, name: str, joints: list[str] | None = None, say=None) -> str:
    """A scenario around a URDF's movable joints: gentle swings around mid-range, funnels containing e(0). Mimic
    joints (a gripper's second finger) are held fixed, and so is every joint not in `joints` when given."""
    from ..core.errors import InputError
    from ..model.tree import bodies_from_tree
    from ..model.urdf import mimic_joints, parse_urdf
    say = say or (lambda s: None)
    tree = parse_urdf(urdf)
    movable = [j.name for j in tree.joints if j.type in ("revolute", "continuous", "prismatic")]
    fixed = list(mimic_joints(urdf))
    if fixed:
        say(f"holding the mimic joint(s) {', '.join(fixed)} fixed (a mimic joint follows another one and is not "
            "controlled on its own)")
    if joints is not None:
        unknown = [j for j in joints if j not in movable]
        if unknown:
            raise InputError(f"names {', '.join(unknown)}, not a movable joint of the URDF", file=str(urdf),
                             key="--joints", expected="names among " + ", ".join(movable))
        fixed += [j for j in movable if j not in joints and j not in fixed]
    if fixed:
        tree = parse_urdf(urdf, fixed=fixed)
    bodies = bodies_from_tree(tree)
    n = len(bodies)
    rel = Path(os.path.relpath(Path(urdf).absolute(), out.absolute().parent)).as_posix()
    home, amp, q0, joints = [], [], [], []
    for b in bodies:
        j = b.joint
        prismatic = j.type == "prismatic"
        d = 0.5 if prismatic else math.pi
        lo = j.lower if j.lower is not None and math.isfinite(j.lower) and j.type != "continuous" else -d
        hi = j.upper if j.upper is not None and math.isfinite(j.upper) and j.type != "continuous" else d
        if not lo < hi:
            lo, hi = lo - 0.1, lo + 0.1
        h = 0.5 * (lo + hi)
        a = min(SWING_PRISMATIC if prismatic else SWING, 0.2 * (hi - lo))
        off = min(OFFSET, 0.1 * (hi - lo))
        home.append(h)
        amp.append(a)
        q0.append(h + off)
        joints.append(f"{_toml_text(j.name)} ({_toml_text(j.type)}, range [{lo:.4g}, {hi:.4g}])")
    ref = [(f"{_fmt(h)} + " if round(h, 6) != 0 else "") + f"{_fmt(a)}*sin({_fmt(0.5 + 0.1 * (i % 5))}*t)"
           for i, (h, a) in enumerate(zip(home, amp))]
    phi0_e2 = _e2_funnel(Path(urdf).absolute().as_posix(), name, ref, q0, n, fixed)
    fixed_line = (f"fixed_joints = {_toml_value(fixed)}   # held at 0: mimic joints and joints not controlled\n"
                  if fixed else "")
    joint_lines = "\n".join(f"#   q{i + 1}: {s}" for i, s in enumerate(joints))
    ref_lines = ",\n     ".join(f'"{r}"' for r in ref)
    return f'''# A scenario written by `symfunnel init --urdf`: the funnel design on the movable joints of
#   {_toml_text(rel)}
# Every key is described in docs/scenario.md. Units are SI: m, kg, s; angles in rad (prismatic joints: m);
# torques in N m (prismatic: N).
# Coordinates, in the URDF's depth-first joint order:
{joint_lines}
# Try: symfunnel derive {_toml_text(str(out))}; symfunnel audit ...; symfunnel simulate ...
# What `symfunnel verify` checks: the model (symmetry, Property 1), the funnels at t = 0, a simulated run (both
# funnels kept, Lyapunov decay, bounded signals) and the interval certificates (input gain, containment, bounds).
# It exits 1 only on an outcome this file does not declare; warnings (an undecided certificate, a vacuous Lyapunov
# level-set argument) never fail it. To declare a finding you expect, e.g. a refuted input-gain assumption:
#   [[expect]]
#   check = "certify.input_gain"
#   status = "fail"
#   reason = "why this design is expected to fail it"
# status = "pass" instead makes a check required (certify.invariance: the Lyapunov argument must close).
name = "{name}"
title = "Funnel control of the {n}-joint robot {_toml_text(Path(urdf).name)} (symfunnel init)"

[model]
type = "urdf"
path = {_toml_value(rel)}   # relative to this file
gravity = [0.0, 0.0, -9.81]       # m/s^2, in the base frame
{fixed_line}
[reference]
# every joint swings gently around the middle of its range (rad or m; t in s)
q = [{ref_lines}]

[initial]
q = [{", ".join(_fmt(x) for x in q0)}]   # {OFFSET} off the reference at t = 0
dq = 0.0

[funnel.e1]                       # F1(t) = phi0 exp(-a t) + phi_inf; contains |e1(0)| <= {OFFSET}
phi0 = 0.1
phi_inf = 0.01
a = 1.0                           # 1/s

[funnel.e2]                       # F2(t) for e2 = dq - alpha2; phi0 is twice the largest |e2(0)| (+ 0.1)
phi0 = {_fmt(phi0_e2)}
phi_inf = 0.05
a = 1.0

[controller]
k1 = 5.0
k2 = 10.0

[adaptation]
gamma = 2.0                       # Gamma = gamma I; larger adapts faster and makes the loop stiffer
sigma = 0.05

[esn]
size = 20
seed = 1
inputs = ["q", "dq", "e1", "e2"]

[plant]                           # what the controller does not know
viscous = 0.2                     # N m s/rad per joint
coulomb = 0.1                     # N m
mass_scale = 1.05                 # the true robot is 5 % heavier than its URDF

[simulation]
t_final = 5.0                     # s
dt = 0.01                         # s
'''


def _toml_value(v) -> str:
    """A string or a list of strings as TOML (json.dumps escaped a character beyond the BMP as a surrogate pair,
    which TOML rejects: a URDF path or joint name with an emoji broke init)."""
    from ..core.toml_write import value
    return value(v)


def _toml_text(s: str) -> str:
    """`s` safe inside a TOML string or comment (quotes, backslashes and control characters replaced)."""
    return "".join(c if c.isprintable() and c not in '"\\' else "_" for c in s)


def _e2_funnel(urdf: str, name: str, ref: list[str], q0: list[float], n: int, fixed=()) -> float:
    """2 max|e2(0)| + 0.1 for this reference and initial state (e2(0) = dq(0) - alpha2(0), from the design)."""
    import tempfile

    import numpy as np

    from ..design import derive, evaluate
    from ..scenario import load_scenario
    probe = (f'name = "{name}"\n[model]\ntype = "urdf"\npath = {_toml_value(str(urdf))}\n'
             + (f'fixed_joints = {_toml_value(list(fixed))}\n' if fixed else '') +
             f'[reference]\nq = [{", ".join(chr(34) + r + chr(34) for r in ref)}]\n'
             f'[initial]\nq = [{", ".join(_fmt(x) for x in q0)}]\n'
             '[funnel.e1]\nphi0 = 0.1\nphi_inf = 0.01\n[funnel.e2]\nphi0 = 1e6\n[esn]\nsize = 1\n')
    with tempfile.TemporaryDirectory(prefix="symfunnel-init-") as tmp:
        p = Path(tmp) / "probe.toml"
        p.write_text(probe, encoding="utf-8")
        d = derive(load_scenario(p))
    vals = evaluate(d, {"t": 0.0, "q": q0, "dq": [0.0] * n}, warn=lambda s: None)
    e2 = np.abs(np.asarray(vals["e2"], dtype=float))
    return float(2 * np.max(e2) + 0.1)
