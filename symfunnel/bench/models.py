"""Bench area `models`: URDF -> M, C, G, exact alpha2_dot and compiled C for serial arms of n = 2..7 joints, each
beside a sympy.physics.mechanics derivation (KanesMethod: mass matrix and forcing vector) of the same arm, in one run.

The arms are the first n joints of the built-in arm7.urdf (the links after joint n are cut off; n = 7 is arm7
itself, tool included). The sympy baseline runs in a child process with a hard time limit (SYMPY_LIMIT_S seconds;
a run that does not finish is reported with baseline_value None and `sympy_status` "did not finish within 60 s",
and larger n are then not attempted). Its M and forcing are checked against symfunnel's at a random state
(`sympy_agreement`, relative).

Results per n (ratio = baseline / symfunnel, higher is better):

- models.build_s.n<n>      seconds from the URDF to M, C, G and every signal of the design (alpha2_dot included),
                           best of BUILD_REPEATS; baseline: sympy KanesMethod seconds for M and forcing only.
- models.ops.n<n>          operations of M, C, G (one CasADi function, CSE); baseline: sympy.count_ops of the
                           Kane M and forcing after sympy.cse. (Ours has the full matrix C; sympy has only C dq + G.)
- models.ops_alpha2_dot.n<n>, models.ops_controller.n<n>   sizes, no baseline.
- models.urdf_to_c_s.n<n>  seconds from the scenario file (URDF) to a compiled shared library of the controller
                           (casadi.CodeGenerator + `cc -O2 -fPIC -shared`, no cache); target 30 s for n = 7.
- models.derive_eval_s.n7  `symfunnel derive arm7 --eval POINT.json` (in-process); target 30 s.

Run as a module for one baseline measurement: `python -m symfunnel.bench.models --sympy ARM.urdf` prints JSON.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

from ._result import result

NS = tuple(range(2, 8))
SYMPY_LIMIT_S = 60.0
BUILD_REPEATS = 5
TARGET_URDF_TO_C_S = 30.0
TARGET_DERIVE_EVAL_S = 30.0
ESN_SIZE = 30                      # as the arm7 scenario
BASELINE = "sympy.physics.mechanics KanesMethod (M, forcing)"


# --- the family of arms ------------------------------------------------------------------------------

def arm7_urdf() -> pathlib.Path:
    """The built-in 7-joint arm's URDF."""
    from ..scenario import DATA_DIR
    return DATA_DIR / "arm7.urdf"


def chain_urdf(n: int, dst: str | os.PathLike, src: str | os.PathLike | None = None) -> pathlib.Path:
    """Write the first n movable joints of `src` (default arm7.urdf) as a URDF: every joint after the n-th movable
    one (in the model's coordinate order) and everything it carries are removed; fixed joints before it stay."""
    from ..model.urdf import movable_joint_names, parse_urdf
    src = pathlib.Path(src or arm7_urdf())
    order = movable_joint_names(parse_urdf(src))
    if not 1 <= n <= len(order):
        raise ValueError(f"n = {n}: the URDF has {len(order)} movable joints")
    tree = ET.parse(src)
    root = tree.getroot()
    joints = root.findall("joint")
    children: dict[str, list[ET.Element]] = {}
    for j in joints:
        children.setdefault(j.find("parent").get("link"), []).append(j)
    cut = set(order[n:])
    drop_links: set[str] = set()
    drop_joints: list[ET.Element] = []

    def drop(link: str) -> None:
        drop_links.add(link)
        for j in children.get(link, []):
            drop_joints.append(j)
            drop(j.find("child").get("link"))

    for j in joints:
        if j.get("name") in cut and j not in drop_joints:
            drop_joints.append(j)
            drop(j.find("child").get("link"))
    for j in drop_joints:
        root.remove(j)
    for lk in root.findall("link"):
        if lk.get("name") in drop_links:
            root.remove(lk)
    root.set("name", f"arm7_first{n}")
    dst = pathlib.Path(dst)
    tree.write(dst, encoding="utf-8", xml_declaration=True)
    return dst


def chain_scenario(urdf: pathlib.Path) -> dict:
    """A minimal scenario (as a parsed TOML table) on a URDF arm, with the arm7 scenario's ESN size."""
    return {"model": {"type": "urdf", "path": str(urdf)}, "reference": {"q": "0.1*sin(t)"},
            "initial": {"q": 0.0}, "esn": {"size": ESN_SIZE}}


# --- symfunnel's side ------------------------------------------------------------------------------

def build_design(raw: dict, base_dir: pathlib.Path):
    """URDF -> scenario (M, C, G) -> design (every signal, alpha2_dot included)."""
    from ..design import derive
    from ..scenario import from_dict
    sc = from_dict(raw, file=str(base_dir / "bench.toml"), base_dir=base_dir)
    return sc, derive(sc)


def compile_controller(design, workdir: pathlib.Path) -> dict:
    """Generate C for Design.controller() and compile it with the C compiler at -O2 into a shared library (no cache)."""
    try:
        from ..emit.c import emit_c
        files = emit_c([design.controller()], "controller")
    except ImportError:      # pragma: no cover - the minimal path, without symfunnel.emit
        import casadi as ca
        cg = ca.CodeGenerator("controller.c", {"with_header": True, "casadi_real": "double", "casadi_int": "int"})
        cg.add(design.controller())
        cg.generate(str(workdir) + "/")
        files = {k: (workdir / k).read_text() for k in ("controller.c", "controller.h")}
    for name, text in files.items():
        (workdir / name).write_text(text, encoding="utf-8")
    cc = _compiler()
    cmd = [cc, "-std=c99", "-O2", "-fPIC", "-shared", "-o", "controller.so", "controller.c", "-lm"]
    proc = subprocess.run(cmd, cwd=workdir, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr.strip()[:2000]}")
    return {"c_bytes": len(files["controller.c"].encode()), "compiler": cc}


def _compiler() -> str:
    try:
        from ..core.ccompile import find_compiler
        return find_compiler()
    except ImportError:      # pragma: no cover
        import shutil
        return os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc") or "cc"


def symfunnel_sizes(sc, design) -> dict:
    """Operation counts of M, C, G (together and apart), of [M, C dq + G], alpha2_dot and the controller."""
    import casadi as ca

    from ..design import count_ops
    m = sc.model
    M, C, G = (design.signals[k] for k in ("M", "C", "G"))

    def ops(*outs):
        return count_ops(ca.Function("f", [m.q, m.dq], list(outs), {"cse": True}))
    return {"ops_MCG": ops(M, C, G), "ops_M": ops(M), "ops_C": ops(C), "ops_G": ops(G),
            "ops_M_Cdq_G": ops(M, ca.mtimes(C, m.dq) + G), "ops_alpha2_dot": design.ops("alpha2_dot"),
            "ops_controller": count_ops(design.controller())}


def _best(fn, repeats: int) -> tuple[float, object]:
    best, out = math.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


# --- the sympy baseline (child process) ------------------------------------------------------------

class _Timeout(BaseException):
    """Raised by SIGALRM; a BaseException so that no `except Exception` inside sympy swallows it."""


def _alarm(seconds: float):
    def handler(signum, frame):
        raise _Timeout()
    signal.signal(signal.SIGALRM, handler)
    signal.setitimer(signal.ITIMER_REAL, seconds)


def kane_equations(urdf: str | os.PathLike, gravity=(0.0, 0.0, -9.81)):
    """sympy.physics.mechanics: the arm of a URDF (bodies merged over fixed joints as symfunnel does) by Kane's
    method; returns (q, u, mass matrix, forcing) with M(q) u' = forcing(q, u) = -(C u + G)."""
    import numpy as np
    import sympy as sp
    from sympy.physics import mechanics as me

    from ..model.tree import bodies_from_tree, skew
    from ..model.urdf import parse_urdf
    bodies = bodies_from_tree(parse_urdf(urdf))
    n = len(bodies)
    q = me.dynamicsymbols(f"q1:{n + 1}")
    u = me.dynamicsymbols(f"u1:{n + 1}")
    N = me.ReferenceFrame("N")
    O = me.Point("O")
    O.set_vel(N, 0)

    def num(x):
        return sp.Float(float(x)) if abs(x) > 1e-14 else sp.Integer(0)

    def vec(frame, v):
        return num(v[0]) * frame.x + num(v[1]) * frame.y + num(v[2]) * frame.z

    frames, origins, rigid, loads = [], [], [], []
    for k, b in enumerate(bodies):
        if b.joint.type == "prismatic":
            raise NotImplementedError("the sympy baseline handles revolute joints only")
        P = N if b.parent < 0 else frames[b.parent]
        Po = O if b.parent < 0 else origins[b.parent]
        A = me.ReferenceFrame(f"A{k + 1}")
        A.orient_explicit(P, sp.Matrix(3, 3, [num(x) for x in b.R0.ravel()]))
        B = me.ReferenceFrame(f"B{k + 1}")
        B.orient_axis(A, vec(A, b.joint.axis), q[k])
        B.set_ang_vel(A, u[k] * vec(A, b.joint.axis))
        Ok = Po.locatenew(f"O{k + 1}", vec(P, b.p0))
        Ok.v2pt_theory(Po, N, P)
        c = b.h / b.mass if b.mass > 0 else np.zeros(3)
        Ic = b.I + b.mass * skew(c) @ skew(c)          # about the centre of mass
        Gk = Ok.locatenew(f"G{k + 1}", vec(B, c))
        Gk.v2pt_theory(Ok, N, B)
        inertia = me.inertia(B, num(Ic[0, 0]), num(Ic[1, 1]), num(Ic[2, 2]), num(Ic[0, 1]), num(Ic[1, 2]),
                             num(Ic[0, 2]))
        rigid.append(me.RigidBody(f"body{k + 1}", Gk, B, num(b.mass), (inertia, Gk)))
        loads.append((Gk, num(b.mass) * vec(N, gravity)))
        frames.append(B)
        origins.append(Ok)
    km = me.KanesMethod(N, q_ind=q, u_ind=u, kd_eqs=[q[i].diff() - u[i] for i in range(n)])
    km.kanes_equations(rigid, loads)
    return q, u, km.mass_matrix, km.forcing


def sympy_baseline(urdf: str, limit: float = SYMPY_LIMIT_S) -> dict:
    """Time the Kane derivation (hard limit), then its size after sympy.cse and its agreement with symfunnel."""
    import numpy as np
    import sympy as sp
    out: dict = {"status": "ok"}
    _alarm(limit)
    try:
        t0 = time.perf_counter()
        q, u, M, forcing = kane_equations(urdf)
        out["seconds"] = time.perf_counter() - t0
    except _Timeout:
        out.update(status="timeout", seconds=None)
        return out
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    exprs = list(M) + list(forcing)
    _alarm(limit)
    try:
        t0 = time.perf_counter()
        out["ops_raw"] = int(sp.count_ops(exprs))
        reps, reduced = sp.cse(exprs)
        out["ops_cse"] = int(sum(sp.count_ops(e) for _, e in reps) + sum(sp.count_ops(e) for e in reduced))
        out["ops_seconds"] = time.perf_counter() - t0
    except _Timeout:
        out["ops_cse"] = None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
    # agreement with symfunnel's model at one random state
    import casadi as ca

    from ..model.urdf import build_urdf
    p = pathlib.Path(urdf)
    m = build_urdf({"type": "urdf", "path": p.name}, file=str(p), base_dir=p.parent)
    n = m.n
    rng = np.random.default_rng(0)
    qv, uv = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    f = sp.lambdify([q, u], [M, forcing], modules="numpy", cse=True)
    Ms, fs = (np.array(a, dtype=float) for a in f(list(qv), list(uv)))
    Mc, rc = (np.array(v) for v in ca.Function("r", [m.q, m.dq], [m.M, ca.mtimes(m.C, m.dq) + m.G])(qv, uv))
    scale = max(np.abs(Mc).max(), np.abs(rc).max(), 1e-12)
    out["agreement"] = float(max(np.abs(Ms - Mc).max(), np.abs(fs.ravel() + rc.ravel()).max()) / scale)
    return out


def run_sympy_child(urdf: pathlib.Path, limit: float = SYMPY_LIMIT_S) -> dict:
    """The baseline in a fresh interpreter (its import time excluded), killed if it overruns the limit badly."""
    cmd = [sys.executable, "-m", "symfunnel.bench.models", "--sympy", str(urdf), "--limit", str(limit)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3 * limit + 60)
    except subprocess.TimeoutExpired:
        return {"status": "timeout", "seconds": None}
    if proc.returncode != 0:
        return {"status": "error", "seconds": None, "error": proc.stderr.strip()[-500:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


# --- the bench ---------------------------------------------------------------------------------------

def run(progress, ns=NS, sympy_limit: float = SYMPY_LIMIT_S, sympy: bool = True) -> list[dict]:
    """Every `models.*` result for the arms of `ns` joints (see the module docstring)."""
    out: list[dict] = []
    skip_sympy_from = None
    with tempfile.TemporaryDirectory(prefix="symfunnel-bench-models-") as tmp:
        tmp = pathlib.Path(tmp)
        for n in ns:
            urdf = chain_urdf(n, tmp / f"arm{n}.urdf")
            raw = chain_scenario(urdf)
            progress(f"models n = {n}: symfunnel URDF -> M, C, G, design (best of {BUILD_REPEATS})")
            build_s, (sc, design) = _best(lambda: build_design(raw, tmp), BUILD_REPEATS)
            sizes = symfunnel_sizes(sc, design)
            progress(f"models n = {n}: URDF -> compiled C")
            work = tmp / f"c{n}"
            work.mkdir()
            t0 = time.perf_counter()
            _, d2 = build_design(raw, tmp)
            cinfo = compile_controller(d2, work)
            c_s = time.perf_counter() - t0

            if not sympy:
                base = {"status": "not run", "seconds": None}
            elif skip_sympy_from is not None:
                base = {"status": f"not run: n = {skip_sympy_from[0]} {skip_sympy_from[1]}", "seconds": None}
            else:
                progress(f"models n = {n}: sympy.physics.mechanics baseline (limit {sympy_limit:g} s)")
                base = run_sympy_child(urdf, sympy_limit)
                if base["status"] == "timeout":
                    base["status"] = f"did not finish within {sympy_limit:g} s"
                    skip_sympy_from = (n, base["status"])
                elif base["status"] != "ok":
                    skip_sympy_from = (n, "failed")
            bs = base.get("seconds")
            status = base["status"]
            common = {"n": n, "arm": f"first {n} joints of arm7.urdf"}
            out.append(result(f"models.build_s.n{n}", build_s, "s", BASELINE, bs,
                              None if bs is None else bs / build_s, sympy_status=status,
                              sympy_agreement=base.get("agreement"), sympy_error=base.get("error"),
                              what="URDF -> M, C, G and every design signal (alpha2_dot included); "
                                   "baseline: M and forcing only", **common))
            bo = base.get("ops_cse")
            out.append(result(f"models.ops.n{n}", sizes["ops_MCG"], "ops", BASELINE + " + sympy.cse", bo,
                              None if bo is None else bo / sizes["ops_MCG"], ops_M=sizes["ops_M"],
                              ops_C=sizes["ops_C"], ops_G=sizes["ops_G"], ops_M_Cdq_G=sizes["ops_M_Cdq_G"],
                              sympy_ops_without_cse=base.get("ops_raw"), sympy_status=status,
                              what="operations of M, C (full matrix), G after CSE; baseline: M and forcing "
                                   "(C dq + G) after sympy.cse, counted by sympy.count_ops", **common))
            out.append(result(f"models.ops_alpha2_dot.n{n}", sizes["ops_alpha2_dot"], "ops", **common))
            out.append(result(f"models.ops_controller.n{n}", sizes["ops_controller"], "ops",
                              esn_units=ESN_SIZE, **common))
            extra = {"target_s": TARGET_URDF_TO_C_S, "meets_target": bool(c_s <= TARGET_URDF_TO_C_S)} if n == 7 else {}
            out.append(result(f"models.urdf_to_c_s.n{n}", c_s, "s", esn_units=ESN_SIZE,
                              what="scenario + URDF -> design -> CodeGenerator C of the controller -> "
                                   "cc -O2 -shared (uncached)", **cinfo, **extra, **common))
        if 7 in ns:
            progress("models: symfunnel derive arm7 --eval")
            out.append(_derive_eval(tmp))
    return out


def _derive_eval(tmp: pathlib.Path) -> dict:
    """What `symfunnel derive arm7 --eval POINT.json --json` does, in-process, at a point inside both funnels:
    load, derive, read the point file, evaluate every signal, write the JSON."""
    from ..core.inputs import loads_json, read_text
    from ..core.io import json_safe
    from ..design import evaluate
    from ..pipeline import Run
    from ..scenario import load_scenario
    sc = load_scenario("arm7")
    point = {"t": 0.0, "q": list(sc.q0), "dq": list(sc.dq0)}
    p = tmp / "point.json"
    p.write_text(json.dumps(point), encoding="utf-8")
    t0 = time.perf_counter()
    design = Run(load_scenario("arm7")).design
    data = loads_json(read_text(str(p), expected="a JSON point file"), file=str(p), expected="a point")
    values = evaluate(design, data, file=str(p))
    text = json.dumps(json_safe({"values": values}), indent=2, allow_nan=False)
    s = time.perf_counter() - t0
    tau = json.loads(text)["values"]["tau"]
    ok = tau is not None and all(math.isfinite(x) for x in tau)
    return result("models.derive_eval_s.n7", s, "s", target_s=TARGET_DERIVE_EVAL_S,
                  meets_target=bool(s <= TARGET_DERIVE_EVAL_S), finite_tau=ok, n=7, arm="arm7")


def _main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(prog="python -m symfunnel.bench.models")
    ap.add_argument("--sympy", metavar="URDF", required=True, help="time the sympy baseline on this URDF")
    ap.add_argument("--limit", type=float, default=SYMPY_LIMIT_S)
    args = ap.parse_args(argv)
    print(json.dumps(sympy_baseline(args.sympy, args.limit)))
    return 0


if __name__ == "__main__":
    sys.exit(_main())
