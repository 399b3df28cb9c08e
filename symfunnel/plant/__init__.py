"""The plant: the true robot the controller does not know — its equations under a commanded torque (`equations`),
the dead zone, friction and disturbance (`nonlinearities`), and a physics engine as the robot (`mujoco`), as SX."""
