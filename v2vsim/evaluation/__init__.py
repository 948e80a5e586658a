"""Scoring a run: `gt` (BEV ground truth on the ego grid), `metrics` (IoU and AP over a run),
`fuse_and_score` (the one prediction path the ego and validation share) and `report` (metrics.json,
report.md, plots)."""
