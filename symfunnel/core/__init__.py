"""The ground floor: errors, safe input and atomic output, validation helpers, names, registries, the wall-clock
deadline, process lifecycle, TOML writing and the C compile cache; imports nothing else of symfunnel."""
