"""What several test folders share: simulated inputs, fake cameras, a subprocess runner of the
command line, the fuzzing library and its nightly command. Nothing here is a test."""

from pathlib import Path

#: The repository root.
REPO = Path(__file__).resolve().parents[2]
