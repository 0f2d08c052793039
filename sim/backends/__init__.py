"""Simulation backends: how each simulator runs the logger's gateware with its device models."""
