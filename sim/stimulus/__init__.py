"""Stimulus: flight scenarios (TOML), the truth they imply, and the sensor byte streams."""
