#!/usr/bin/env python3
"""Demo of the soft_twin digital twin (placeholder, see `make demo`)."""


def main() -> int:
    print("demo not yet implemented")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
