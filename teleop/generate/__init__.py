"""Generating demonstrations from a few sources (MimicGen's method): the plan and the runner."""
