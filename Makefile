# The two commands of the README. Both install what they need first (idempotent).
PYTHON ?= python3
PIP = $(PYTHON) -m pip install --disable-pip-version-check -q

.PHONY: install demo test clean-install bench zoo zoo-camera

install:
	$(PIP) torch==2.13.0
	$(PIP) -e ".[dev]"

demo: install
	v2vsim run scenarios/intersection.yaml

# deptry: every third-party import declared in pyproject.toml, every declared package imported ([tool.deptry]).
# The suite installs the wheel into a venv that sees none of this machine's packages (tests/test_wheel.py).
test: install
	$(PYTHON) -m ruff check .
	$(PYTHON) -m deptry .
	$(PYTHON) -m pytest -n 2 --maxschedchunk 2 --durations=20  # two workers (pytest-xdist), the long tests first, two at a time (tests/conftest.py)

# Before a release: the README's own install steps and the wheel, each in a fresh venv without the system's packages.
clean-install:
	scripts/clean_install.sh

bench: install
	v2vsim bench sensors
	v2vsim bench models
	v2vsim bench comm

# Rebuild the LiDAR model zoo from scratch: dataset (data/lidar) + every training stage (README "Training").
zoo: install
	scripts/lidar_zoo.sh data/lidar runs/train

# Rebuild the camera model zoo from scratch: dataset with cameras (data/camera), every SinBEVT stage, LaRa's
# none + cobevt (README "Training").
zoo-camera: install
	scripts/camera_zoo.sh data/camera runs/train_camera
