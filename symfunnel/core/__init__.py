"""The ground floor: errors, safe input and atomic output, validation helpers, names, registries, the wall-clock
deadline, process lifecycle, TOML writing, the C compile cache, scipy's Sobol points and Nelder-Mead (without
importing scipy.stats or scipy.optimize); imports nothing else of symfunnel."""
