"""One normalisation of camera model names (pipeline.compat), shared by the compatibility
check and the dark library: libgphoto2, EXIF and user spellings of one model match, distinct
models whose names share a prefix do not."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hdrcap.pipeline import compat
from hdrcap.pipeline.calibration.darklibrary import DarkLibrary, same_camera

#: (name a, name b, same model?) as the three sources spell real cameras
PAIRS = [
    ("Nikon DSC D750", "NIKON CORPORATION NIKON D750", True),  # libgphoto2 vs EXIF make + model
    ("Nikon D750", "D750", True),
    ("Canon EOS 5D Mark II", "Canon Inc. Canon EOS 5D Mark II", True),
    ("Nikon DSC D750", "Nikon DSC D7500", False),  # a prefix of another model's name
    ("NIKON CORPORATION NIKON D7500", "Nikon D750", False),
    ("Canon EOS 5D Mark II", "Canon EOS 5D Mark III", False),
    ("Sony A7", "Sony A7R", False),
    ("", "Nikon D750", True),  # unknown matches any
]


@pytest.mark.parametrize("a, b, same", PAIRS)
def test_dark_library_and_compat_agree_on_model_names(a, b, same):
    assert same_camera(a, b) is same and same_camera(b, a) is same
    assert compat.same_model(a, b) is same


def test_the_dark_library_uses_the_one_model_rule():
    assert same_camera is compat.same_model


@given(st.text(alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 -", min_size=1, max_size=12))
def test_a_brand_or_company_word_in_front_does_not_change_the_model(model):
    assert same_camera(model, f"NIKON CORPORATION {model}") and same_camera(f"Nikon DSC {model}", model)


def test_dark_library_finds_the_exif_spelling_and_not_a_longer_model(tmp_path):
    lib = DarkLibrary(tmp_path / "lib")
    lib.add(np.full((2, 2), 100.0), 4, camera="NIKON CORPORATION NIKON D750", iso=100, exposure_time=0.5)
    lib.add(np.full((2, 2), 200.0), 4, camera="NIKON CORPORATION NIKON D7500", iso=100, exposure_time=0.5)
    hit = lib.find(camera="Nikon DSC D750", iso=100, exposure_time=0.5)  # the name libgphoto2 reports
    assert hit is not None and hit.camera.endswith("D750") and hit.level == 100.0
    assert lib.find(camera="Nikon DSC D7500", iso=100, exposure_time=0.5).level == 200.0
    assert lib.find(camera="Nikon Z6", iso=100, exposure_time=0.5) is None
