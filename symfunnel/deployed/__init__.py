"""The controller as deployed: the compiled generated C step in a sampled-data loop with zero-order hold, the
minimum sample rate that keeps the funnels, and the report's data about both."""
