"""Synthetic data with known answers (calibration rigs, scenes) for tests, samples and demos."""
