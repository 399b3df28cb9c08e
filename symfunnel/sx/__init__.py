"""CasADi SX utilities: the instruction tape, exact SX -> sympy, small linear algebra and sympy proofs under a time limit."""
