"""Scoring a run: `gt` (BEV ground truth on the ego grid), `metrics` (IoU and AP over a run),
`fuse_and_score` (the one prediction path the ego and validation share), `block_bootstrap` (intervals over frames),
`status` (what a run's status says) and its outputs: `report` writes metrics.json (`metrics_doc`), report.md
(`report_md`) and the plots (`run_plots`) from the ego's `RunSummary` (`run_summary`); `fleet_report` merges the
egos' metrics.json and report.md into the run's when several CAVs drive."""
