"""Checker mutation testing: seeded errors in the checking code itself, and whether the test suite notices.

`verify --mutants` measures how well the gate catches a wrong *design*; this measures how well the tests catch a
wrong *checker*. Each mutant of `MUTANTS` is one literal source edit (``old`` -> ``new``, which must match exactly
once, so a refactor that removes its target makes the tool fail loudly instead of testing nothing) in a temporary
copy of the repository. The tests run against it are those whose coverage context (pytest-cov,
``--cov-context=test``, from one baseline run of the unmutated suite) covers a mutated line, fastest first, stopping
at the first failure. A mutant is *killed* when a test fails (or the run exceeds its time limit), *survived*
otherwise, *equivalent* when its entry carries a written argument that it cannot change any outcome (not run;
score = killed / (total - equivalent)).

    python -m symfunnel.bench.checker_mutants [--only ID ...] [--list] [--fresh] [--state DIR] [--all-tests]

The baseline and every mutant's outcome are kept in the state directory (default `.pytest_cache/checker-mutants`
of the repository), keyed by a hash of the sources, so an interrupted run resumes where it stopped. It needs a
source checkout (the tests) and the `test` extra (pytest-cov); `symfunnel bench --only verify` reports its score as
`verify.checker_mutation_score`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

#: the classes of seeded errors (issue "Verify the verifier")
CLASSES = ("comparison", "tolerance", "index", "constant", "clamp", "sign", "statistic")


@dataclass(frozen=True)
class CheckerMutant:
    """One seeded error of the checking code: a literal edit of one file, its class, and for an equivalent mutant
    the argument why no outcome can change."""

    id: str
    file: str
    old: str
    new: str
    kind: str
    description: str
    equivalent: str | None = None


def _m(id, file, old, new, kind, description, equivalent=None):
    return CheckerMutant(id, file, old, new, kind, description, equivalent)


V, T, AU, LY, BS = ("symfunnel/checks/verify.py", "symfunnel/checks/theory.py", "symfunnel/checks/audit.py",
                    "symfunnel/checks/lyapunov.py", "symfunnel/design/backstepping.py")
CO, IM, LO, ST = ("symfunnel/checks/consistency.py", "symfunnel/checks/implementation.py",
                  "symfunnel/deployed/loop.py", "symfunnel/emit/step.py")
RA, CA, FU = "symfunnel/deployed/rate.py", "symfunnel/campaigns/campaign.py", "symfunnel/family/funnels.py"
CS = "symfunnel/campaigns/statistics.py"
BA, SE, RE, PR = ("symfunnel/sx/batch_rules.py", "symfunnel/sx/search.py", "symfunnel/certificates/region.py",
                  "symfunnel/certificates/problem.py")
IN, IG, BO, SC = ("symfunnel/certificates/invariance.py", "symfunnel/certificates/input_gain.py",
                  "symfunnel/certificates/bounds.py", "symfunnel/certificates/selfcheck.py")
PF, CN = "symfunnel/certificates/projection_face.py", "symfunnel/certificates/containment.py"

MUTANTS: tuple[CheckerMutant, ...] = (
    # --- funnel containment (checks/verify.py)
    _m("containment_cannot_fail", V, 'status = "pass" if mmin > 0 else "fail"',
       'status = "pass" if mmin > -np.inf else "fail"', "comparison", "the containment comparison can no longer fail"),
    _m("containment_non_strict", V, 'status = "pass" if mmin > 0 else "fail"',
       'status = "pass" if mmin >= 0 else "fail"', "comparison", "|e| = F counted as inside (the funnel is open)"),
    _m("containment_joint_off_by_one", V, "m = np.asarray(s[mk])[:, j]", "m = np.asarray(s[mk])[:, j - 1]",
       "index", "the per-joint margin read from the neighbouring joint"),
    # --- Lyapunov decay and bound along the run
    _m("decay_tolerance_1e3", V, "viol = finite & (margin < -allow)", "viol = finite & (margin < -1e3 * allow)",
       "tolerance", "the decay inequality's round-off allowance loosened by 10^3"),
    _m("decay_comparison_flipped", V, "viol = finite & (margin < -allow)", "viol = finite & (margin > allow)",
       "comparison", "decay violations counted where it holds"),
    _m("bound_tolerance_1e3", V, "allow = REL_TOL * np.abs(B) + abs_allow",
       "allow = 1e3 * REL_TOL * np.abs(B) + abs_allow", "tolerance", "the bound's allowance loosened by 10^3"),
    _m("bound_includes_t0", V, "    ok[0] = False                      # B(0) = V(0): equality by construction\n",
       "", "index", "the bound also compared at t = 0",
       equivalent="integrated_bound evaluates V0 * exp(-rho * 0) + delta/rho * (1 - exp(0)) = V0 * 1.0 + 0.0, which "
                  "is V(0) exactly in floating point, so the margin at t = 0 is exactly 0 >= -allowance: including "
                  "the point can never add a violation, nor change the worst point unless every other margin is "
                  "also >= 0 (then the reported worst margin is 0 either way)"),
    # --- bounded.*
    _m("tau_split_shortened", V, "q = max(1, int(0.75 * len(t)))", "q = max(1, int(0.7 * len(t)))", "clamp",
       "the 'last quarter' of bounded.tau starts earlier"),
    _m("tau_allowance_doubled", V, "TAU_GROWTH_ALLOWANCE = 0.1", "TAU_GROWTH_ALLOWANCE = 0.2", "tolerance",
       "bounded.tau tolerates twice the growth"),
    _m("w_hat_bound_gamma", V, "np.sqrt(2 * float(res.gamma) *", "np.sqrt(float(res.gamma) *", "constant",
       "the W_hat bound without the factor 2 of V >= ||W~||^2/(2 gamma)"),
    _m("x_esn_tolerance_1e3", V, "box * (1 + 1e-9)", "box * (1 + 1e-6)", "tolerance",
       "the reservoir box's allowance loosened by 10^3"),
    _m("x_esn_box_doubled", V, "box = 1.0 / float(design.scenario.esn.leak)",
       "box = 2.0 / float(design.scenario.esn.leak)", "constant", "the reservoir box twice as large"),
    # --- the proof's checks (checks/theory.py)
    _m("identity_tolerance_1e3", T, "IDENTITY_TOL = 1e-9", "IDENTITY_TOL = 1e-6", "tolerance",
       "the identity tolerance loosened by 10^3"),
    _m("identity_tolerance_1e6", T, "IDENTITY_TOL = 1e-9", "IDENTITY_TOL = 1e-3", "tolerance",
       "the identity tolerance loosened by 10^6 (the issue's example)"),
    _m("identity_without_eps", T, "pts[\"eps\"] = rng.normal(0.0, 10.0, (n, k))", "pts[\"eps\"] = np.zeros((n, k))",
       "constant", "the identity evaluated with eps = 0 (the unknown's coupling untested)"),
    _m("rho_positive_non_strict", T, "    if rho > 0:\n        return CheckResult(\"lyapunov.rho_positive\", \"pass\"",
       "    if rho >= 0:\n        return CheckResult(\"lyapunov.rho_positive\", \"pass\"", "comparison",
       "rho = 0 counted as decay"),
    _m("guarantee_z_bound", T, "z_bound = float(np.sqrt(2 * max(V0, V_ult)))", "z_bound = float(np.sqrt(max(V0, V_ult)))",
       "constant", "|z| <= sqrt(V) instead of sqrt(2 V)"),
    _m("guarantee_threshold", T, "GUARANTEE_MIN_MARGIN = 0.05", "GUARANTEE_MIN_MARGIN = 0.1", "constant",
       "the guarantee's vacuity threshold altered"),
    _m("input_gain_largest_eigenvalue", T, "lam = np.linalg.eigvalsh(S)[:, 0]", "lam = np.linalg.eigvalsh(S)[:, -1]",
       "index", "the input gain's largest eigenvalue instead of its smallest"),
    _m("input_gain_left_slopes_only", T, "np.round([lo_l[j], hi_l[j], lo_r[j], hi_r[j]], 12)",
       "np.round([lo_l[j], hi_l[j]], 12)", "index", "the right branch's slopes never combined"),
    # --- the variant's Lyapunov constants (design/backstepping.py)
    _m("rho_k2_doubled", BS, "ca.mmin(k2 * s[\"mu2\"]))", "ca.mmin(2 * k2 * s[\"mu2\"]))", "constant",
       "rho doubled in its k2 term (the issue's example)"),
    _m("delta_half_k2", BS, "delta = ca.sum1(s[\"mu2\"] * eps ** 2 / (2 * k2))",
       "delta = ca.sum1(s[\"mu2\"] * eps ** 2 / k2)", "constant", "delta's Young term without the 1/2"),
    _m("delta_sigma_term", BS, "delta = delta + sigma / 2 * ca.sumsqr(W_star)",
       "delta = delta + sigma * ca.sumsqr(W_star)", "constant", "delta's sigma/2 ||W*||^2 doubled"),
    _m("rho_lower_k1", BS, "out = min(float(np.min(2 * np.asarray(sc.k1) / F1_sup))",
       "out = min(float(np.min(np.asarray(sc.k1) / F1_sup))", "constant", "the constant rho bound without 2 k1"),
    # --- Lyapunov evaluation (checks/lyapunov.py)
    _m("rel_tol_1e3", LY, "REL_TOL = 1e-8", "REL_TOL = 1e-5", "tolerance", "the round-off allowance loosened 10^3"),
    _m("decay_margin_sign", LY, "margin = rhs - V_dot", "margin = V_dot - rhs", "sign", "the decay margin's sign"),
    _m("integrated_bound_rho", LY, "return V0 * e + (delta / rho) * (1 - e)", "return V0 * e + delta * (1 - e)",
       "constant", "the integrated bound's ultimate value delta instead of delta/rho"),
    _m("rho_lower_inf_F", LY, "sup1 = extremes(sc.funnels[\"e1\"], t_final)[1]",
       "sup1 = extremes(sc.funnels[\"e1\"], t_final)[0]", "index", "inf F1 where the bound needs sup F1"),
    # --- the audit (checks/audit.py)
    _m("audit_tolerance_1e3", AU, "    if rel[j] > a.tolerance:", "    if rel[j] > 1e3 * a.tolerance:", "tolerance",
       "the model identities' tolerance loosened by 10^3"),
    _m("pd_without_refinement", AU, "for j in np.argsort(lmin)[:3]:", "for j in np.argsort(lmin)[:0]:", "clamp",
       "positive definiteness from the samples alone (no local minimisation)"),
    _m("funnel_parameters_strict", AU, "if not f.phi0[i] >= f.phi_inf[i] > 0:", "if not f.phi0[i] > f.phi_inf[i] > 0:",
       "comparison", "phi0 = phi_inf rejected"),
    _m("initial_condition_last_joint", AU, "bad = [i for i in range(n) if not abs(e1[i]) < F1[i]]",
       "bad = [i for i in range(n - 1) if not abs(e1[i]) < F1[i]]", "index", "the last joint's e1(0) never checked"),
    _m("claim_best_entry", AU, "rel_pt = rel.max(axis=(0, 2))", "rel_pt = rel.min(axis=(0, 2))", "statistic",
       "a printed claim judged by its best-agreeing entry"),
    # --- the twins (checks/consistency.py, family/funnels.py)
    _m("twin_tolerance_1e3", CO, "TWIN_TOL = 1e-9", "TWIN_TOL = 1e-6", "tolerance",
       "the twins' tolerance loosened by 10^3"),
    _m("twin_fd_tolerance_1e3", CO, "FD_TOL = 1e-6", "FD_TOL = 1e-3", "tolerance",
       "the finite-difference tolerance loosened by 10^3"),
    _m("twin_second_derivative_unchecked", CO, '("ddq_d = d/dt dq_d (AD)", ddqd, d_dqd, TWIN_TOL)',
       '("ddq_d = d/dt dq_d (AD)", ddqd, ddqd, TWIN_TOL)', "index", "ddq_d compared with itself"),
    _m("funnel_extremes_sup_is_inf", FU, "return vals.min(axis=1), vals.max(axis=1)",
       "return vals.min(axis=1), vals.min(axis=1)", "statistic", "sup F taken as inf F"),
    # --- the deployed controller: its checks, the sampled loop, the generated step
    _m("saturation_one_sided", LO, "(np.abs(self.tau) >= tm * (1 - 1e-12))", "(self.tau >= tm * (1 - 1e-12))",
       "clamp", "saturation counted at +tau_max only"),
    _m("sampled_min_margin_e1_only", LO, "        m = m[np.all(np.isfinite(m), axis=1)]\n",
       "        m = m[np.all(np.isfinite(m), axis=1)][:, :self.q.shape[1]]\n", "index",
       "the sampled loop's min margin over e1 only"),
    _m("sampled_breach_e1_only", LO, "bad = np.where(~(M > 0).all(axis=1) & good)[0]",
       "bad = np.where(~(M[:, :n] > 0).all(axis=1) & good)[0]", "index", "a sampled-loop breach of e2 not detected"),
    _m("loop_delay_shortened", LO, "            p_u[:] = pending\n            pending[:] = taubuf\n",
       "            pending[:] = taubuf\n            p_u[:] = pending\n", "clamp",
       "the one-sample delay of the sampled loop shortened to none (the hold applies the new torque at once)"),
    _m("implementation_containment_non_strict", IM, '"pass" if r.min_margin > 0 else "fail"',
       '"pass" if r.min_margin >= -1e-3 else "fail"', "tolerance", "the deployed loop allowed a margin of -1e-3"),
    _m("step_clamp_one_sided", ST, "tau = ca.fmin(ca.fmax(tau, -tm), tm)", "tau = ca.fmin(tau, tm)", "clamp",
       "the generated step's saturation limits +tau only (the issue's example)"),
    _m("step_projection_one_sided", ST, "q_c = qd + ca.fmin(ca.fmax(e1, -CLIP * F1), CLIP * F1)",
       "q_c = qd + ca.fmin(e1, CLIP * F1)", "clamp", "the step's projection onto the e1 funnel on one side only"),
    _m("step_update_sign", ST, "x_next = x_esn + etd[0] * xdot", "x_next = x_esn - etd[0] * xdot", "sign",
       "the reservoir's discrete update with the wrong sign"),
    _m("step_update_factor_index", ST, "w_next = w_hat + etd[1] * wdot", "w_next = w_hat + etd[0] * wdot", "index",
       "W_hat advanced with the reservoir's exponential-Euler weight"),
    _m("step_explicit_euler", ST, "    return -math.expm1(-rate * h) / rate", "    return h", "constant",
       "phi(l) = h (explicit Euler) instead of (1 - exp(-l h))/l"),
    _m("step_margin_without_abs", ST, "margin = ca.vertcat(1 - ca.fabs(e1) / F1, 1 - ca.fabs(e2) / F2)",
       "margin = ca.vertcat(1 - e1 / F1, 1 - ca.fabs(e2) / F2)", "sign", "the step's e1 margin one-sided"),
    # --- the rate search and the campaign's statistics
    _m("rate_holds_or", RA, "ok = res.ok and mt >= margin", "ok = res.ok or mt >= margin",
       "comparison", "a rate whose run breached may count as holding"),
    _m("rate_tolerance_10x", RA, "while hi / lo > 1 + rel_tol:", "while hi / lo > 1 + 10 * rel_tol:", "tolerance",
       "the bisection stops at 10x its tolerance"),
    _m("clopper_pearson_lower_one_sided", CS, "float(beta.ppf(a / 2, k, n - k + 1))", "float(beta.ppf(a, k, n - k + 1))",
       "statistic", "the lower end of the breach interval computed one-sided"),
    _m("clopper_pearson_upper_one_sided", CS, "float(beta.ppf(1 - a / 2, k + 1, n - k))",
       "float(beta.ppf(1 - a, k + 1, n - k))", "statistic", "the upper end computed one-sided"),
    _m("breach_probability_counts_failed", CS, '"breach_probability": breaches / decided if decided else None',
       '"breach_probability": breaches / runs if runs else None', "statistic",
       "failed runs counted in the breach probability's denominator"),
    _m("row_breach_wrong_funnel", CA, '        if b["funnel"] == "e1":\n', '        if b["funnel"] != "e1":\n', "index",
       "a located breach's margin written to the other funnel's column"),
    # --- the certificates' machinery (sx/, certificates/): each rule's ends, the widening, the eigenvalue bound,
    # the regions, the level sets, the refutations' conditions and the self-check
    _m("widening_removed", BA, "TRANSCENDENTAL_ULPS = 8", "TRANSCENDENTAL_ULPS = 0", "tolerance",
       "transcendental results not widened for libm's error (only one ulp outward)"),
    _m("exp_lower_end_unrounded", BA, "return np.maximum(_wdn(np.exp(al)), 0.0), _wup(np.exp(ah)), None",
       "return np.maximum(np.exp(al), 0.0), _wup(np.exp(ah)), None", "clamp",
       "exp's lower end taken from libm as is (neither widened nor rounded down)"),
    _m("sin_extrema_swapped", BA, "_periodic(np.sin, al, ah, 0.5 * math.pi, -0.5 * math.pi)",
       "_periodic(np.sin, al, ah, -0.5 * math.pi, 0.5 * math.pi)", "sign",
       "sin's interior maximum and minimum looked for at each other's phase"),
    _m("cosh_upper_end_from_lower", BA, "return np.maximum(_wdn(np.cosh(lo)), 1.0), _wup(np.cosh(hi)), None",
       "return np.maximum(_wdn(np.cosh(lo)), 1.0), _wup(np.cosh(lo)), None", "index",
       "cosh's upper end evaluated at the smaller |x|"),
    _m("gershgorin_without_off_diagonal", SE, "off = np.nextafter(A.sum(axis=2) * grow, _INF)",
       "off = np.nextafter(0.0 * A.sum(axis=2) * grow, _INF)", "constant",
       "the eigenvalue bound's discs without their off-diagonal radii"),
    _m("gershgorin_den_without_q_discs", SE,
       "den = np.nextafter((np.diagonal(QH, axis1=1, axis2=2) + AQ.sum(axis=2)) * grow, _INF)",
       "den = np.nextafter(np.diagonal(QH, axis1=1, axis2=2) * grow, _INF)", "constant",
       "the bound's denominator without Q = L L^T's off-diagonal discs"),
    _m("pd_refutes_at_nan", SE, "if np.isfinite(lam) and lam <= 0:", "if not lam > 0:", "comparison",
       "a NaN lambda_min counted as a refutation"),
    _m("joint_box_half_tube", RE, "float(np.nextafter(a - F1[j], -np.inf)), float(np.nextafter(b + F1[j], np.inf))",
       "float(np.nextafter(a - 0.5 * F1[j], -np.inf)), float(np.nextafter(b + 0.5 * F1[j], np.inf))", "constant",
       "the input gain's joint box from half the e1 funnel"),
    _m("slope_span_halved", RE, "SLOPE_SPAN = 10.0", "SLOPE_SPAN = 5.0", "clamp",
       "the dead zone's slopes enclosed over half the torque span"),
    _m("region_half_width", PR, '"s1": (-np.ones(n), np.ones(n)), "s2": (-np.ones(n), np.ones(n)),',
       '"s1": (-0.5 * np.ones(n), 0.5 * np.ones(n)), "s2": (-0.5 * np.ones(n), 0.5 * np.ones(n)),', "clamp",
       "the funnel region R_m built half as wide as it declares"),
    _m("level_without_half", IN, "c_max = 0.5 * zc * zc", "c_max = zc * zc", "constant",
       "the level a margin allows without the 1/2 of V = z^2/2"),
    _m("input_gain_low_vertices_only", IG, "(dl[j], dh[j]) if j in wide_d else (dl[j],)",
       "(dl[j],) if j in wide_d else (dl[j],)", "index", "only the slope box's lower vertex searched"),
    _m("slopes_not_attained", IG, "return np.where(s_ <= 0.5 * (dl + dh), seen_lo, seen_hi)", "return s_",
       "index", "a refutation re-checked at the rigorous hull's slopes, not at slopes the dead zone attains"),
    _m("saturation_witness_outside_ball", BO, "    if dist <= r:\n        return point, None",
       "    if dist <= 10 * r:\n        return point, None", "tolerance",
       "a saturation witness accepted outside the proven W_hat ball"),
    _m("selfcheck_disabled", SC, "    if below or above:", "    if False:", "comparison",
       "the certificates' self-check never fires"),
    # --- certify.containment with a projected W_hat law (certificates/projection_face.py, containment.py)
    _m("projection_boundary_test_unchecked", PF, "    if not ca.is_equal(c, ca.fmax(a, 0) * k, 2):",
       "    if False:", "comparison", "the projection's c accepted without its boundary test max(a, 0)"),
    _m("projection_radius_at_layer", PF, "w = outer_radius(P[\"R\"], P[\"eps\"]) * (1.0 + W_MARGIN)",
       "w = P[\"R\"] * (1.0 + W_MARGIN)", "constant", "the W_hat ball proven at R, inside the boundary layer"),
    _m("filippov_sign_of_midpoint", CN, "        HI[:, self.sidx] = np.where(DH < 0, -1.0, 1.0)",
       "        HI[:, self.sidx] = np.where(DH < 0, -1.0, 1.0)\n"
       "        LO[:, self.sidx] = HI[:, self.sidx] = np.sign(0.5 * DL + 0.5 * DH)", "sign",
       "sign(g) taken at the box's midpoint, not Filippov's hull over the box"),
)

#: files and folders of the repository the copies need (the tests read docs/, derivations/ and README.md)
_COPY_IGNORE = (".git", ".venv", "venv", ".pytest_cache", "__pycache__", "*.egg-info", "reports", ".mypy_cache",
                "*.so", "*.o", "site")


class MutantError(RuntimeError):
    """A mutant that cannot be applied (its `old` text is not in its file exactly once) or a failed baseline."""


def repo_root() -> Path:
    """The source checkout this package runs from (the tool needs its tests)."""
    return Path(__file__).resolve().parent.parent.parent


def apply(text: str, m: CheckerMutant) -> str:
    """The file's text with the mutant's edit; MutantError unless `old` occurs exactly once."""
    count = text.count(m.old)
    if count != 1:
        raise MutantError(f"mutant {m.id}: its text occurs {count} times in {m.file} (expected exactly once): "
                          f"{m.old.strip()[:80]!r}")
    return text.replace(m.old, m.new, 1)


def mutated_lines(text: str, m: CheckerMutant) -> list[int]:
    """The 1-based line numbers of the original file that the edit touches."""
    start = text.index(m.old)
    first = text.count("\n", 0, start) + 1
    return list(range(first, first + max(1, m.old.rstrip("\n").count("\n") + 1)))


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _digest(root: Path, package: str) -> str:
    """A hash of what every test's coverage depends on: the package's sources (this tool's own file aside: its
    mutant list changes no coverage) and the tests' shared helpers."""
    h = hashlib.sha256()
    files = sorted(p for p in (root / package).rglob("*.py") if p.name != Path(__file__).name)
    files += sorted(p for p in (root / "tests").rglob("*.py") if not p.name.startswith("test_"))
    for p in files:
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def test_files(root: Path) -> dict[str, str]:
    """{tests/...test_*.py: sha} of the suite."""
    return {p.relative_to(root).as_posix(): _sha(p) for p in sorted((root / "tests").rglob("test_*.py"))}


def _copy(root: Path, dest: Path) -> None:
    shutil.copytree(root, dest, symlinks=True, ignore=shutil.ignore_patterns(*_COPY_IGNORE), dirs_exist_ok=True)


def _env(copy: Path, cache: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(copy)
    env["SYMFUNNEL_CACHE"] = str(cache)
    env.pop("COVERAGE_PROCESS_START", None)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def _run(cmd: list[str], cwd: Path, env: dict, timeout: float | None) -> tuple[int | None, str, float]:
    """(return code or None on timeout, the output's tail, seconds); the whole process group is stopped."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out:
        p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            rc = p.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            rc = None
        except BaseException:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            raise
        out.seek(0)
        tail = out.read()[-3000:]
    return rc, tail, time.perf_counter() - t0


def baseline(root: Path, state: Path, *, package: str = "symfunnel", marker: str | None = "not slow",
             workers: int = 2, progress=None, cache: Path | None = None) -> dict:
    """The unmutated suite under coverage with per-test contexts, cached by a hash of the package's sources:
    {"digest", "files", "contexts": {file: {line: [test ids]}}, "durations": {test id: s}, "failed": [test ids]}.

    With the sources unchanged, only the test files that changed (or are new) since the cached run are measured
    again, so adding a test costs its own file's run, not the suite's."""
    say = progress or (lambda s: None)
    digest = _digest(root, package)
    path = state / f"baseline-{digest}-{(marker or 'all').replace(' ', '_')}.json"
    files = test_files(root)
    old = json.loads(path.read_text()) if path.exists() else None
    if old is not None:
        todo = sorted(f for f, h in files.items() if old["files"].get(f) != h)
        gone = set(old["files"]) - set(files)
        if not todo and not gone:
            return old
    else:
        todo, gone = sorted(files), set()
    state.mkdir(parents=True, exist_ok=True)
    cache = cache or state / "compile-cache"
    stale = set(todo) | gone
    if old is None:
        out = {"digest": digest, "marker": marker, "files": {}, "contexts": {}, "durations": {}, "failed": [],
               "seconds": 0.0}
    else:
        out = old
        keep = lambda t: t.split("::", 1)[0] not in stale          # noqa: E731
        out["contexts"] = {f: {ln: [t for t in ts if keep(t)] for ln, ts in lines.items()}
                           for f, lines in out["contexts"].items()}
        out["durations"] = {t: d for t, d in out["durations"].items() if keep(t)}
        out["failed"] = [t for t in out["failed"] if keep(t)]
        out["files"] = {f: h for f, h in out["files"].items() if f not in stale}
    if todo:
        with tempfile.TemporaryDirectory(prefix="symfunnel-baseline-") as tmp:
            copy = Path(tmp) / "repo"
            _copy(root, copy)
            junit = Path(tmp) / "junit.xml"
            cov = Path(tmp) / ".coverage"
            cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--cov={package}",
                   "--cov-context=test", "--cov-report=", f"--junitxml={junit}", "-o", "junit_family=xunit1"]
            if marker:
                cmd += ["-m", marker]
            import importlib.util
            if workers > 1 and importlib.util.find_spec("xdist") is not None:
                cmd += ["-n", str(workers)]
            cmd += todo if old is not None else []
            env = _env(copy, cache)
            env["COVERAGE_FILE"] = str(cov)
            say(f"checker mutants: baseline run under coverage of {len(todo)} test files")
            rc, tail, secs = _run(cmd, copy, env, None)
            if rc not in (0, 1, 5) or (rc != 5 and not cov.exists()):
                raise MutantError(f"the baseline test run failed (exit {rc}):\n{tail}")
            if rc != 5:
                durations, failed = _junit(junit)
                out["durations"].update(durations)
                out["failed"] = sorted(set(out["failed"]) | set(failed))
                for f, lines in _contexts(cov, copy, package).items():
                    mine = out["contexts"].setdefault(f, {})
                    for ln, ts in lines.items():
                        mine[ln] = sorted(set(mine.get(ln, [])) | set(ts))
            out["seconds"] = out.get("seconds", 0.0) + secs
    out["files"].update({f: files[f] for f in todo})
    out["digest"] = digest
    path.write_text(json.dumps(out))
    return out


def _sha_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _junit(path: Path) -> tuple[dict[str, float], list[str]]:
    """Per-test durations and the failing tests of a junit file, as pytest node ids."""
    import xml.etree.ElementTree as ET
    durations, failed = {}, []
    for case in ET.parse(path).getroot().iter("testcase"):
        file = case.get("file") or case.get("classname", "").replace(".", "/") + ".py"
        nodeid = f"{file}::{case.get('name')}"
        durations[nodeid] = float(case.get("time") or 0.0)
        if any(ch.tag in ("failure", "error") for ch in case):
            failed.append(nodeid)
    return durations, failed


def _contexts(cov_file: Path, copy: Path, package: str) -> dict[str, dict[str, list[str]]]:
    """{file relative to the repository: {line: [test node ids whose context covers it]}}."""
    from coverage import CoverageData
    data = CoverageData(basename=str(cov_file))
    data.read()
    out: dict[str, dict[str, list[str]]] = {}
    for f in data.measured_files():
        try:
            rel = Path(f).resolve().relative_to(copy.resolve()).as_posix()
        except ValueError:
            continue
        if not rel.startswith(package + "/"):
            continue
        lines: dict[str, list[str]] = {}
        for line, ctxs in (data.contexts_by_lineno(f) or {}).items():
            tests = sorted({c.rsplit("|", 1)[0] for c in ctxs if c})
            if tests:
                lines[str(line)] = tests
        out[rel] = lines
    return out


def select_tests(base: dict, m: CheckerMutant, text: str) -> list[str]:
    """The tests whose coverage context covers a line the mutant edits, fastest first (failing ones left out).

    A line that runs only at import (a module-level constant: no test's context covers it, the import happens at
    collection) acts through the module's functions, so it selects every test that covers a line of its module."""
    lines = base["contexts"].get(m.file, {})
    chosen = set()
    for ln in mutated_lines(text, m):
        chosen.update(lines.get(str(ln), []))
    if not chosen and _module_level(text, m):
        for tests in lines.values():
            chosen.update(tests)
    chosen -= set(base["failed"])
    dur = base["durations"]
    return sorted(chosen, key=lambda t: (dur.get(t, 1e9), t))


def _module_level(text: str, m: CheckerMutant) -> bool:
    """Whether the mutant edits a statement at the top level of its module (no indentation)."""
    start = text.index(m.old)
    line_start = text.rfind("\n", 0, start) + 1
    return not text[line_start:start].strip() and not text[line_start:line_start + 1].isspace()


def run_mutant(root: Path, m: CheckerMutant, tests: list[str], base: dict, *, cache: Path,
               timeout_factor: float = 3.0) -> dict:
    """Apply one mutant in a temporary copy and run its tests: {"status": killed|survived, "by", "tests", ...}."""
    src = (root / m.file).read_text(encoding="utf-8")
    mutated = apply(src, m)
    row = {"id": m.id, "file": m.file, "kind": m.kind, "description": m.description, "tests": len(tests)}
    if not tests:
        row.update(status="survived", by=None, seconds=0.0, note="no test covers the mutated lines")
        return row
    budget = sum(base["durations"].get(t, 5.0) for t in tests)
    with tempfile.TemporaryDirectory(prefix=f"symfunnel-mutant-{m.id}-") as tmp:
        copy = Path(tmp) / "repo"
        _copy(root, copy)
        (copy / m.file).write_text(mutated, encoding="utf-8")
        junit = Path(tmp) / "junit.xml"
        cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", "-p", "no:randomly",
               f"--junitxml={junit}", "-o", "junit_family=xunit1", *tests]
        rc, tail, secs = _run(cmd, copy, _env(copy, cache), timeout_factor * budget + 120.0)
        by = None
        if rc is None:
            status, note = "killed", f"timeout after {secs:.0f} s"
        elif rc == 0:
            status, note = "survived", f"{len(tests)} covering tests pass"
        else:
            # under pytest-xdist (-n in addopts) -x ends a run with a failure as "interrupted", exit 2: the junit
            # file says whether a test failed (killed by it) or nothing ran (the mutant breaks collection)
            by = next(iter(_junit(junit)[1]), None) if junit.exists() else None
            status = "killed"
            note = "" if by is not None else f"pytest exit {rc} (the mutant breaks collection or the run)"
    row.update(status=status, by=by, seconds=round(secs, 2), note=note)
    return row


def run(*, only=None, root: Path | None = None, state: Path | None = None, mutants=MUTANTS, package="symfunnel",
        marker: str | None = "not slow", workers: int = 2, fresh: bool = False, progress=None) -> dict:
    """Every (or the `only`) mutant through its covering tests; resumable. Returns the summary:
    {"score", "mutants", "killed", "survived", "equivalent": [{"id", "argument"}], "rows": [...]}."""
    say = progress or (lambda s: None)
    root = Path(root or repo_root())
    if not (root / "tests").is_dir():
        raise MutantError(f"no tests/ beside {root / package}: checker mutation testing needs a source checkout")
    state = Path(state or root / ".pytest_cache" / "checker-mutants")
    cache = state / "compile-cache"
    chosen = [m for m in mutants if not only or m.id in only]
    if only and len(chosen) != len(set(only)):
        raise MutantError(f"unknown mutant id(s): {sorted(set(only) - {m.id for m in mutants})}")
    ids = [m.id for m in mutants]
    if len(set(ids)) != len(ids):
        raise MutantError("duplicate mutant ids")
    texts = {}
    for m in chosen:                                   # every edit must apply before anything runs
        texts.setdefault(m.file, (root / m.file).read_text(encoding="utf-8"))
        apply(texts[m.file], m)
        if m.kind not in CLASSES:
            raise MutantError(f"mutant {m.id}: class {m.kind!r} is not one of {CLASSES}")
    base = baseline(root, state, package=package, marker=marker, workers=workers, progress=say, cache=cache)
    results_path = state / f"results-{base['digest']}.json"
    done = {} if fresh or not results_path.exists() else json.loads(results_path.read_text())
    rows = []
    for i, m in enumerate(chosen):
        if m.equivalent:
            rows.append({"id": m.id, "file": m.file, "kind": m.kind, "description": m.description,
                         "status": "equivalent", "argument": m.equivalent})
            continue
        tests = select_tests(base, m, texts[m.file])
        # an outcome is kept while the mutant, the tests chosen for it and those tests' files are unchanged
        key = _sha_text(json.dumps([asdict(m), tests, {f: base["files"].get(f) for f in
                                                       sorted({t.split("::", 1)[0] for t in tests})}], sort_keys=True))
        if key in done:
            rows.append(done[key])
            say(f"checker mutant {i + 1}/{len(chosen)} {m.id}: {done[key]['status']} (kept from an earlier run)")
            continue
        say(f"checker mutant {i + 1}/{len(chosen)} {m.id}: {len(tests)} covering tests")
        row = run_mutant(root, m, tests, base, cache=cache)
        say(f"checker mutant {i + 1}/{len(chosen)} {m.id}: {row['status']}"
            + (f" by {row['by']}" if row.get("by") else "") + (f" ({row['note']})" if row.get("note") else ""))
        done[key] = row
        results_path.write_text(json.dumps(done, indent=1))
        rows.append(row)
    return summarize(rows)


def summarize(rows: list[dict]) -> dict:
    """score = killed / (total - equivalent), with the survivors and the equivalence arguments."""
    total = len(rows)
    killed = sum(r["status"] == "killed" for r in rows)
    eq = [{"id": r["id"], "argument": r["argument"]} for r in rows if r["status"] == "equivalent"]
    survived = [r["id"] for r in rows if r["status"] == "survived"]
    live = total - len(eq)
    return {"score": killed / live if live else 1.0, "mutants": total, "killed": killed, "survived": survived,
            "equivalent": eq, "classes": sorted({r["kind"] for r in rows}), "rows": rows}


def main(argv=None) -> int:
    """Command line: run the mutants (resumable), print one line per mutant and the score; exit 1 below 0.9."""
    ap = argparse.ArgumentParser(prog="python -m symfunnel.bench.checker_mutants", description=__doc__.split("\n")[0])
    ap.add_argument("--only", action="append", metavar="ID", help="run this mutant (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--fresh", action="store_true", help="ignore the outcomes of earlier runs")
    ap.add_argument("--state", type=Path, help="where the baseline and the outcomes are kept")
    ap.add_argument("--all-tests", action="store_true", help="include the tests marked slow in the baseline")
    ap.add_argument("--workers", type=int, default=2, help="pytest-xdist workers of the baseline run (default 2)")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    a = ap.parse_args(argv)

    def stop(signum, frame):                      # SIGTERM: stop the running pytest's process group too
        raise SystemExit(128 + signum)
    signal.signal(signal.SIGTERM, stop)
    if a.list:
        for m in MUTANTS:
            print(f"{m.id:<40} {m.kind:<11} {m.file}: {m.description}" + (" [equivalent]" if m.equivalent else ""))
        return 0
    try:
        out = run(only=a.only, state=a.state, marker=None if a.all_tests else "not slow", workers=a.workers,
                  fresh=a.fresh, progress=lambda s: print(s, file=sys.stderr, flush=True))
    except MutantError as exc:
        print(f"symfunnel: error: {exc}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(out, indent=2))
    else:
        for r in out["rows"]:
            print(f"{r['id']:<40} {r['status']:<10} {r.get('by') or r.get('argument', '') or r.get('note', '')}")
        print(f"score {out['score']:.3f}: {out['killed']} killed of {out['mutants']} "
              f"({len(out['equivalent'])} equivalent, {len(out['survived'])} survived)")
    return 0 if out["score"] >= 0.9 else 1


if __name__ == "__main__":
    sys.exit(main())
