"""Capture: a stage's neural character and capture ring -> skinning -> renderer -> dataset on disk."""
