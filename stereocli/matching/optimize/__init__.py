"""Optimizers: turn a cost volume into a disparity map (WTA, SGM, DP, SO, BP, GC, ...)."""
