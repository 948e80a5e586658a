"""Datasets recorded from the simulator: writing (`record`), the on-disk layout (`layout`), reading its frames
(`store`) and the PyTorch reader (`torch_dataset`); OPV2V's layout (`opv2v_layout`), written (`opv2v_write`) and
read (`opv2v_read`). The formats are documented in docs/dataset.md."""
