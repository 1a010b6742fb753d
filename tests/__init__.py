"""hdrcap's tests: one folder per package (tests/pipeline/, tests/acquire/, ...), helpers shared by
several folders in :mod:`tests.helpers` (docs/testing.md describes the layout)."""
