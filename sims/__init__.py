"""The simulated lab: firmware simulators speaking the real protocols, the synthetic scene and sensor."""
