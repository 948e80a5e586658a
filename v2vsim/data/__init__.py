"""Datasets recorded from the simulator: writing (`record`), the on-disk layout (`layout`) and the
PyTorch reader (`torch_dataset`). The format is documented in docs/dataset.md."""
