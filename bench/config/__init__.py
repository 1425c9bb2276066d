"""The parts' configuration schemas (controller, estimator, plant): below the scenario, which loads them from TOML."""
