"""Policies and the environments they run in: Gymnasium envs, evaluation, policy takeover in a served session."""
