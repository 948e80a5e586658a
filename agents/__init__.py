"""Process entry points: simulator driver, CAV perception agent, ego fusion agent."""
