"""The plant: what the real robot does beyond the controller's model (dead zone, friction, disturbance), as SX."""
