"""The ground floor: errors, safe input and atomic output, validation helpers, names, registries, the wall-clock
deadline, process lifecycle, TOML writing, the C compile cache and scipy's Sobol points without scipy.stats;
imports nothing else of symfunnel."""
