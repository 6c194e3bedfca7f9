"""Environments whose step queries a trained world model instead of physics."""
