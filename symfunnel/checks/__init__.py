"""The checks: the audit of the model and the printed claims, the proof's own checks (design identity, Lyapunov
constants, guarantee, input gain), verify on the trajectories, the deployed loop's checks and the gate that compares
every outcome with what the scenario declares."""
