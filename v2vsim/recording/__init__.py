"""The Rerun recording of a run: what each CAV sends for it (scan), what is drawn in 3D
(world3d) and on the BEV grid (bev), the default layout (blueprint), and the Recorder that logs
a run's frames. `v2vsim view RUN_DIR` opens it (view)."""
