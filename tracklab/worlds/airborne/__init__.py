"""Airborne radar four-coordinate tracking in the antenna frame (paper 001)."""
