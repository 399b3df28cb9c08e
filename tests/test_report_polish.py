"""The report reads well: long formulas laid out in lines with named parts (and the parts rebuild the formula
exactly), round-off terms dropped for display only, stretchy fences, matrices in details as tables, figures with
legends outside the data, containment on a log scale, an unclipped torque axis, PNG/PDF export, captions naming the
paper's figures."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from symfunnel.reporting import figures as FIG
from symfunnel.reporting import formula as FM

q1, q2, qd, t = sympy.symbols("q1 q2 qd1 t", real=True)


def _e2():
    e = q1 - qd
    F = sympy.Rational(1, 100) + sympy.Rational(9, 50) * sympy.exp(-2 * t)
    return q2 + 5 * e / (F - sympy.Abs(e)) + 9 * e * sympy.exp(-2 * t) / (25 * F)


def _rebuild(defs):
    """The expression the laid-out lines stand for: signed terms summed, named parts substituted back."""
    exprs = {}
    for sym, rows in defs:
        total = 0
        for row in rows:
            for sign, term in row:
                total += -term if sign == "-" else term
        exprs[sym] = total
    root = exprs.pop(None)
    for _ in range(len(exprs) + 1):
        root = root.xreplace(exprs)
    return root


@pytest.mark.parametrize("budget", [8.0, 14.0, 30.0])
def test_layout_rebuilds_the_formula_and_every_line_fits(budget):
    e2 = _e2()
    z2 = e2 / (sympy.Rational(1, 100) + 2 * sympy.exp(-2 * t) / 5 - sympy.Abs(e2))
    defs = FM.lines(z2, budget)
    assert sympy.simplify(_rebuild(defs) - z2) == 0
    # and numerically, independently of sympy's simplifier
    f0 = sympy.lambdify((q1, q2, qd, t), z2)
    f1 = sympy.lambdify((q1, q2, qd, t), _rebuild(defs))
    rng = np.random.default_rng(3)
    for x in rng.uniform(-0.01, 0.01, size=(20, 4)):
        assert f1(*x) == pytest.approx(f0(*x), rel=1e-12)
    for _, rows in defs:
        for row in rows:
            w = sum(FM.width(term) + (1.3 if sign else 0) for sign, term in row)
            assert len(row) == 1 or w <= budget
    if budget < FM.width(z2):
        assert len(defs) > 1 or len(defs[0][1]) > 1          # it was broken up, not left as one long line


def test_width_grows_with_the_expression():
    assert FM.width(q1) < FM.width(q1 + q2) < FM.width(q1 + q2 + sympy.sin(t))
    assert FM.width(_e2()) > 20


def test_noise_is_dropped_for_display_only():
    g = 9.81 * sympy.sin(q2) + 8.7e-14 * sympy.cos(q1) * sympy.sin(q2) + 1.5e-3 * q1 - 3.0e-16
    shown, n = FM.drop_noise(g)
    assert n == 2
    assert shown.has(sympy.sin(q2)) and shown.coeff(q1) == pytest.approx(1.5e-3)
    assert not shown.has(sympy.cos(q1))
    f0, f1 = sympy.lambdify((q1, q2), g), sympy.lambdify((q1, q2), shown)
    for x in np.random.default_rng(1).uniform(-3, 3, size=(50, 2)):
        assert abs(f0(*x) - f1(*x)) <= 1e-13
    # a matrix uses one common scale: a small but real entry elsewhere stays
    M = sympy.Matrix([[9.81 * sympy.sin(q2) + 1e-15 * q1], [2e-3 * sympy.cos(q1)]])
    Ms, k = FM.drop_noise(M)
    assert k == 1 and Ms[1] == M[1] and not Ms[0].has(q1)
    # exact models are untouched
    assert FM.drop_noise(_e2()) == (_e2(), 0)


def test_floats_are_rounded_for_display():
    from symfunnel.reporting.mathml import mathml_body
    e, _ = FM.present(0.00247487373415181 * sympy.sin(q1))
    (f,) = e.atoms(sympy.Float)
    assert float(f) == pytest.approx(0.00247487373415181, rel=1e-6)
    assert "<mn>0.00247487</mn>" in mathml_body(e)


def test_fences_stretch_and_mfenced_is_rewritten():
    from symfunnel.reporting.mathml import mathml_body
    m = mathml_body(sympy.Matrix([[q1, 1 / (q1 + q2)], [0, q2]]))
    assert "<mo>[</mo>" not in m and '<mo stretchy="true" symmetric="true" fence="true">[</mo>' in m
    src = '<mfenced open="[" close="]"><mi>a</mi><mfenced><mi>b</mi><mi>c</mi></mfenced></mfenced>'
    out = FM.stretchy_fences(src)
    assert "mfenced" not in out
    assert out.count('stretchy="true"') == 4 and out.count('separator="true"') == 2
    assert out.index(">[<") < out.index("<mi>a</mi>") < out.index(">(<") < out.index("<mi>b</mi>") \
        < out.index("<mi>c</mi>") < out.index(">)<") < out.index(">]<")


def test_matrix_in_a_detail_becomes_a_table():
    from symfunnel.reporting.text import detail_html
    h = str(detail_html("N = Matrix([\n[2*a*sin(q2), f(b, c)],\n[d < 0,      0]]); done"))
    assert "Matrix(" not in h and h.count("<tr>") == 2 and h.count("<td>") == 4
    assert "<code>f(b, c)</code>" in h and "d &lt; 0" in h and h.endswith("; done")
    assert str(detail_html("Matrix([1, 2")) == "Matrix([1, 2"        # not a matrix literal: plain text


def test_builtin_scenario_header(paper):
    from symfunnel.reporting.sections import file_shown
    assert file_shown(paper) == "built-in: paper"


# --- figures ---------------------------------------------------------------------------------------

class _Res:
    """A trajectory with a known torque peak and known errors (no simulation needed)."""

    def __init__(self, n=2, T=400):
        self.t = np.linspace(0.0, 4.0, T)
        F1 = 0.18 * np.exp(-2 * self.t)[:, None] + 0.01 + 0 * np.ones((1, n))
        F2 = 0.4 * np.exp(-2 * self.t)[:, None] + 0.01 + 0 * np.ones((1, n))
        e1 = 0.5 * F1 * np.sin(3 * self.t)[:, None] * 10.0 ** (-np.arange(n))[None, :]
        tau = 8.0 * np.sin(self.t)[:, None] * np.ones((1, n))
        tau[3, :] = [502.0, -310.0][:n] if n <= 2 else 502.0
        self.signals = {"q": e1, "qd": 0 * e1, "e1": e1, "F1": F1, "e2": 0.3 * F2, "F2": F2, "tau": tau,
                        "tau_applied": 0.9 * tau}
        self.status = "ok"
        self.breach = None


def _no_legend_over_data(fig):
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    for ax in fig.axes:
        leg = ax.get_legend()
        if leg is None:
            continue
        lb = leg.get_window_extent(r)
        for other in fig.axes:
            assert not lb.overlaps(other.get_window_extent(r)), "legend over an axes"


@pytest.mark.parametrize("name", ["tracking", "funnel", "torque", "funnel_margin"])
def test_legends_are_outside_the_axes(name):
    import matplotlib.pyplot as plt
    res = _Res()
    args = {"tracking": (res, 2), "funnel": (res, 2, "e1"), "torque": (res, 2, None),
            "funnel_margin": (res, 2)}[name]
    fig = getattr(FIG, name).figure(*args)
    try:
        _no_legend_over_data(fig)
    finally:
        plt.close(fig)


def test_torque_axis_holds_the_peak():
    import matplotlib.pyplot as plt
    res = _Res()
    fig = FIG.torque.figure(res, 2, None)
    try:
        for j, ax in enumerate(fig.axes):
            lo, hi = ax.get_ylim()
            tau = res.signals["tau"][:, j]
            assert lo <= tau.min() and hi >= tau.max()
            assert ax.get_yscale() == "symlog"            # 502 against a typical 8: the rest stays readable
    finally:
        plt.close(fig)


def test_margin_plot_shows_containment_on_a_log_scale():
    import matplotlib.pyplot as plt
    res = _Res()
    fig = FIG.funnel_margin.figure(res, 2)
    try:
        for j, ax in enumerate(fig.axes):
            assert ax.get_yscale() == "log"
            lo, hi = ax.get_ylim()
            assert hi > 1.0                                # the boundary is in view
            y = ax.get_lines()[0].get_ydata()              # |e1|/F1 of this joint, computed independently here
            ratio = np.abs(res.signals["e1"][:, j]) / res.signals["F1"][:, j]
            assert np.nanmax(y) == pytest.approx(ratio.max(), rel=1e-9)
            assert lo <= max(np.nanmin(y[y > 0]), 1e-8)     # small ratios are on the axis, not flattened to 0
    finally:
        plt.close(fig)


def test_export_writes_png_and_pdf(tmp_path):
    res = _Res()
    svg = FIG.tracking(res, 2, export_to=(tmp_path, "fig01-tracking"))
    assert svg.startswith("<svg")
    png, pdf = (tmp_path / "fig01-tracking.png").read_bytes(), (tmp_path / "fig01-tracking.pdf").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and pdf.startswith(b"%PDF")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig01-tracking.pdf", "fig01-tracking.png"]


def test_figures_option_rejects_a_file_before_any_work(tmp_path, capsys):
    from symfunnel.cli import main
    f = tmp_path / "f"
    f.write_text("x")
    assert main(["report", "paper", "--figures", str(f), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("symfunnel: error:") and "--figures" in err[0]


def test_captions_name_the_paper_figures_only_when_the_source_is_the_paper(paper):
    from symfunnel.reporting.sections import figure_caption
    from symfunnel.scenario import load_scenario
    c = figure_caption("torque", "Torque", paper)
    assert "Reproduces Figure 8" in c and "Control signals" in c and "of the source" in c
    arm7 = load_scenario("arm7")
    assert figure_caption("tracking", "Tracking", arm7) == "Tracking."          # arm7 cites no paper
    assert figure_caption("weights", "W", paper) == "W."


def test_joint_one_formulas_for_seven_joints():
    """n = 7: F1, z1 and alpha2 are still shown (their joint-1 entries), not just their sizes."""
    from symfunnel.design import derive
    from symfunnel.reporting.sections import derivation_section
    from symfunnel.scenario import load_scenario
    d = derive(load_scenario("arm7"))
    sec = derivation_section(d, [], lambda s: None)
    rows = {r["name"]: r for r in sec["signals"]}
    for k in ("F1", "z1"):
        assert rows[k]["mathml"] and "<math" in rows[k]["mathml"], k
    assert "<math" in sec["alpha2"]["alpha2"]          # alpha2 (joint 1) once, in the section of the exact alpha2_dot


def test_a_formula_says_when_round_off_was_left_out():
    from symfunnel.reporting.mathml import formula_html
    h = formula_html("<mi>G</mi>", 9.81 * sympy.sin(q2) + 8.7e-14 * sympy.cos(q1), 50.0)
    assert "1 term(s) with a coefficient below 1e-10" in h and "8.7" not in h and "9.81" in h
    assert "term(s)" not in formula_html("<mi>G</mi>", 9.81 * sympy.sin(q2) + 0.5 * sympy.cos(q1), 50.0)
