"""A process for tests/v2vsim/test_launch.py to start warm: it runs the Python code it is given."""

from __future__ import annotations


def main(argv: list[str]) -> int:
    exec(argv[0], {"__name__": "__probe__"})  # noqa: S102 - the test's own code
    return 0


if __name__ == "__main__":  # started cold (`python -m`), as a request the zygote does not fit is
    import sys

    sys.exit(main(sys.argv[1:]))
