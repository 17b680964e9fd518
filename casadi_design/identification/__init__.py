"""Identify a robot from measured data: read, register, fit, compensate, export."""
