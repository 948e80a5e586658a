"""Studies over many runs: `v2vsim sweep` (grid x seeds), with bootstrap confidence intervals."""
