"""Closed-loop longitudinal planning of the ego from what a perception method perceived (pure numpy)."""
