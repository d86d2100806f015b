"""Victim models: the detectors under attack."""
