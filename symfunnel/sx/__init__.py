"""The ground floor: CasADi SX utilities every layer may use (instruction tape, exact SX -> sympy), importing nothing above."""
