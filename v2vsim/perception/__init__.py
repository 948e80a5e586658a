"""Models as the running simulator uses them: `build` (which models and weights a scenario runs),
`encode` (the CAV side: features and its own outputs) and `fuse` (the ego side: warp, fuse, decode)."""
