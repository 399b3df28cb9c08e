"""Example: run the generated controller (symfunnel_controller.py, numpy only) over a recorded trajectory.

    python run_trajectory.py trajectory.txt

Each line of the trajectory holds the controller's inputs in manifest order (matrices column-major); lines
starting with '#' are comments. Prints t and tau per sample, like main.c of the C output. All rows are evaluated
in one call (a trailing batch axis).
"""

import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import symfunnel_controller as ctl  # noqa: E402


def main(path="trajectory.txt"):
    data = np.loadtxt(path, comments="#", ndmin=2).T          # (values per row, samples)
    entry = next(e for e in ctl.MANIFEST if e["name"] == "controller")
    args, row = [], 0
    for d in entry["inputs"]:
        r, c = d["shape"]
        args.append(data[row:row + r * c].reshape(r, c, -1, order="F"))
        row += r * c
    if row != data.shape[0]:
        sys.exit(f"{path}: rows hold {data.shape[0]} numbers, the controller takes {row}")
    tau = ctl.controller(*args)[0]                              # (n, 1, samples)
    n = tau.shape[0]
    print("# t " + " ".join(f"tau{i + 1}" for i in range(n)))
    for j in range(tau.shape[2]):
        print(" ".join(repr(float(v)) for v in [args[0][0, 0, j], *tau[:, 0, j]]))


if __name__ == "__main__":
    main(*sys.argv[1:2])
