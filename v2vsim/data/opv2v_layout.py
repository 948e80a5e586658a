"""The OPV2V dataset layout (OpenCOOD's docs/md_files/data_intro.md, data_annotation_tutorial.md): its folder and
file names, the splits and BEV ground-truth files, and its YAML dialect; what the writer (v2vsim.data.opv2v_write)
and the reader (v2vsim.data.opv2v_read) share.

    <root>/<train|validate|test>/<scenario>/data_protocol.yaml
    <root>/<split>/<scenario>/<cav id>/<NNNNNN>.pcd | .yaml | _camera0..3.png | _bev_*.png

docs/dataset.md, "OPV2V format", has the conversion table and what is derived or absent.
"""

from __future__ import annotations

import re
from pathlib import Path

import yaml

from v2vsim.data.layout import DatasetError

PROTOCOL = "data_protocol.yaml"
# v2vsim split -> OPV2V split folder, and back (OPV2V's test_culvercity and other test_* are eval splits too).
SPLIT_DIRS = {"train": "train", "val": "validate", "eval": "test"}
DIR_SPLITS = {"train": "train", "validate": "val", "validation": "val", "val": "val", "test": "eval"}
# v2vsim mask -> the BEV ground-truth file of OPV2V's camera track (OpenCOOD logreplay / CoBEVT names).
MASK_FILES = {"dynamic": "bev_dynamic", "road": "bev_static", "lane": "bev_lane",
              "visible_self": "bev_visibility", "visible": "bev_visibility_corp"}
REQUIRED_MASKS = ("dynamic", "road", "lane")  # the others can be derived from the `vehicles` lists
CAMERAS = 4
OPV2V_BEV_SIZE_M = 100.0  # CoBEVT / logreplay: radius 50 m, 256 x 256 px
OPV2V_RANGE_M = 70.0  # OpenCOOD's COM_RANGE
OPV2V_RATE_HZ = 10.0
EXTRA = "v2vsim"  # our own key in a CAV's yaml and in data_protocol.yaml (OpenCOOD reads neither)
STEM = re.compile(r"^(-?[0-9]+)\.yaml$")
CAV_DIR = re.compile(r"^-?[0-9]+$")


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml's parser when PyYAML has it
    """Safe YAML with floats such as `1e-05` (no dot) read as floats, as OpenCOOD's loader does."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?|[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)"
               r"|\.[0-9_]+(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+0123456789."))


def load_yaml(path: Path) -> dict:
    try:
        doc = yaml.load(path.read_text(), Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except (OSError, yaml.YAMLError) as e:
        raise DatasetError(f"{path}: unreadable YAML ({e})") from None
    if not isinstance(doc, dict):
        raise DatasetError(f"{path}: expected a mapping at the top")
    return doc


def dump_yaml(doc: dict, path: Path) -> None:
    dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
    path.write_text(yaml.dump(doc, Dumper=dumper, default_flow_style=None, sort_keys=True))
