"""Read the instruction tape of an SX casadi.Function into plain Python data, shared by sx2sympy and the Python emitter."""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import casadi

#: opcode -> name without the "OP_" prefix, e.g. casadi.OP_ADD -> "ADD".
OP_NAMES: dict[int, str] = {getattr(casadi, n): n[3:] for n in sorted(dir(casadi)) if n.startswith("OP_")}

#: Tape bookkeeping that is not an arithmetic operation (excluded from operation counts).
BOOKKEEPING = frozenset(getattr(casadi, "OP_" + n) for n in ("INPUT", "OUTPUT", "CONST", "ASSIGN", "PARAMETER"))


class Instruction(NamedTuple):
    """One tape instruction: opcode, argument work slots, result slot(s) and the constant (OP_CONST only).

    A named tuple rather than a frozen dataclass: read_tape builds one per instruction, and a frozen dataclass's
    __init__ (object.__setattr__ per field) was a third of its time on a large tape."""

    op: int
    args: tuple[int, ...]
    res: tuple[int, ...]
    constant: float | None = None

    @property
    def name(self) -> str:
        """The opcode's name without the OP_ prefix."""
        return OP_NAMES.get(self.op, f"<{self.op}>")


@dataclass(frozen=True)
class Tape:
    """An SX function's straight-line program plus the shapes and nonzero positions of its inputs and outputs."""

    function: casadi.Function
    instructions: tuple[Instruction, ...]
    n_work: int
    in_names: tuple[str, ...]
    out_names: tuple[str, ...]
    in_shapes: tuple[tuple[int, int], ...]
    out_shapes: tuple[tuple[int, int], ...]
    #: per input/output: column-major linear index (row + col*nrows) of each structural nonzero
    in_nz: tuple[tuple[int, ...], ...]
    out_nz: tuple[tuple[int, ...], ...]
    #: free SX variables, in the order their OP_PARAMETER instructions appear on the tape
    free: tuple[casadi.SX, ...]


def as_sx_function(f: casadi.Function) -> casadi.Function:
    """Return `f` itself when it is an SXFunction, else its SX expansion, so that there is a scalar tape to read."""
    if not isinstance(f, casadi.Function):
        raise TypeError(f"expected a casadi.Function, got {type(f).__name__}")
    if f.is_a("SXFunction"):
        return f
    try:
        return f.expand()
    except Exception as exc:  # casadi raises a plain RuntimeError
        raise TypeError(f"function {f.name()!r} is not an SXFunction and cannot be expanded: {exc}") from exc


def read_tape(f: casadi.Function) -> Tape:
    """Read every instruction of `f` (an SX function, or one that expands to SX) once, in tape order."""
    f = as_sx_function(f)
    op_const = casadi.OP_CONST
    ins = []
    for k in range(f.n_instructions()):
        op = f.instruction_id(k)
        const = f.instruction_constant(k) if op == op_const else None
        ins.append(Instruction(op, tuple(f.instruction_input(k)), tuple(f.instruction_output(k)), const))
    free = tuple(f.free_sx()) if f.has_free() else ()
    return Tape(
        function=f,
        instructions=tuple(ins),
        n_work=int(f.sz_w()),
        in_names=tuple(f.name_in()),
        out_names=tuple(f.name_out()),
        in_shapes=tuple((f.size1_in(i), f.size2_in(i)) for i in range(f.n_in())),
        out_shapes=tuple((f.size1_out(i), f.size2_out(i)) for i in range(f.n_out())),
        in_nz=tuple(tuple(int(j) for j in f.sparsity_in(i).find()) for i in range(f.n_in())),
        out_nz=tuple(tuple(int(j) for j in f.sparsity_out(i).find()) for i in range(f.n_out())),
        free=free,
    )


def count_ops(f: casadi.Function) -> dict:
    """Count the tape's real operations (not INPUT/OUTPUT/CONST/ASSIGN/PARAMETER), to report a function's size."""
    f = as_sx_function(f)
    by_op: dict[str, int] = {}
    total = 0
    n = f.n_instructions()
    for k in range(n):
        op = f.instruction_id(k)
        if op in BOOKKEEPING:
            continue
        total += 1
        name = OP_NAMES.get(op, str(op))
        by_op[name] = by_op.get(name, 0) + 1
    return {"operations": total, "instructions": n, "by_op": dict(sorted(by_op.items()))}
