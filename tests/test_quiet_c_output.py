"""Row 22 of issue 21: what CasADi and IPOPT print themselves (C-level writes to fds 1 and 2, CasADi's own
warnings through sys.stdout) is silenced during the call and summarised in one line; the user's lines still show."""

from __future__ import annotations

import subprocess
import sys
import textwrap

PROG = textwrap.dedent("""
    import ctypes, os, sys, warnings
    import casadi as ca
    from symfunnel.core import lifecycle
    lifecycle.install()
    x = ca.SX.sym("x")
    with lifecycle.quiet_c_output("IPOPT") as q:
        os.write(1, b"raw fd 1\\n")
        os.write(2, b"raw fd 2\\n")
        ctypes.CDLL(None).printf(b"printf from C\\n")
        print("python print")
        solver = ca.nlpsol("s", "ipopt", {"x": x, "f": (x - 3) ** 2})     # IPOPT's banner and iteration table
        sol = solver(x0=0)
        print(lifecycle.user_stderr() is not sys.stderr, file=lifecycle.user_stderr())
        lifecycle.announce("the closing line")
    print(f"after: x = {float(sol['x']):.6f}, silenced {q['lines']}")
    lifecycle.uninstall()
    """)


def test_solver_output_is_silenced_and_summarised_in_one_line():
    p = subprocess.run([sys.executable, "-c", PROG], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    out, err = p.stdout, p.stderr
    for noise in ("raw fd", "printf from C", "python print", "Ipopt", "EXIT:", "iter"):
        assert noise not in out and noise not in err.replace("IPOPT: ", ""), (noise, out, err)
    assert out.strip().splitlines() == [out.strip().splitlines()[0]]
    assert out.startswith("after: x = 3.000000, silenced ")
    silenced = int(out.split("silenced ")[1])
    assert silenced > 20                                 # the banner, the options, the table, the statistics
    lines = err.strip().splitlines()
    assert lines[:2] == ["True", "the closing line"]     # the user's lines reached the terminal during the block
    assert len(lines) == 3 and lines[2].startswith(f"symfunnel: warning: IPOPT: {silenced} line(s) of CasADi/solver "
                                                   "output silenced, the first message: ")


def test_nothing_printed_means_no_summary_line():
    prog = textwrap.dedent("""
        from symfunnel.core import lifecycle
        lifecycle.install()
        with lifecycle.quiet_c_output("x") as q:
            pass
        print(q["lines"])
        """)
    p = subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and p.stdout.strip() == "0" and p.stderr == "", p.stderr
