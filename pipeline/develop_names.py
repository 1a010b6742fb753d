"""Names of ``hdrcap develop``'s options (demosaicing methods, output spaces), without numpy.

The command line imports them for its ``--help`` text; :mod:`pipeline.develop` does the work.
"""

from __future__ import annotations

__all__ = ["DEMOSAIC_METHODS", "LINEAR_METHODS", "OUTPUT_SPACES"]

#: Demosaicing methods: name -> colour_demosaicing function name.
DEMOSAIC_METHODS: dict[str, str] = {
    "bilinear": "demosaicing_CFA_Bayer_bilinear",
    "malvar2004": "demosaicing_CFA_Bayer_Malvar2004",
    "menon2007": "demosaicing_CFA_Bayer_Menon2007",
}
#: The methods that are linear filters of the mosaic (sigma propagated).
LINEAR_METHODS = frozenset({"bilinear", "malvar2004"})
#: Output colour spaces.
OUTPUT_SPACES = ("camera", "xyz", "linear-srgb")
