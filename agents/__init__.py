"""Process entry points: simulator driver, CAV perception agent, ego fusion agent, and the ego over a recording
(`v2vsim evaluate`: evaluate)."""
