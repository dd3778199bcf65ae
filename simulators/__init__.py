"""Simulated devices and world: they implement the same interfaces as the real drivers."""
