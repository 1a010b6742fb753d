"""The one result of a merge: irradiance, its uncertainty, the flags and the header.

:class:`HdrResult` goes from the merge kernel (:meth:`hdrcap.pipeline.merge.accumulator.
MergeAccumulator.result`) through the self-calibration, the denoiser and every writer
(:func:`hdrcap.pipeline.io.results.write_result`); the Python API returns it as it is.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hdrcap.pipeline.schema import CHANNEL_NAMES

__all__ = ["HdrResult", "summarise"]


@dataclass(frozen=True, eq=False)
class HdrResult:
    """A merged HDR image, per photosite of the raw mosaic (never demosaiced).

    Attributes
    ----------
    irradiance : numpy.ndarray
        float32 (H, W), the irradiance X (Eq. 12) in ``header["unit"]`` (electrons per second
        per photosite; DN/s when the gain is unknown). Where ``nexp == 0`` it is a lower bound
        (saturated) or a defect's placeholder. Never NaN or infinite; dark photosites may be
        negative.
    sigma : numpy.ndarray
        float32 (H, W), total standard uncertainty of ``irradiance``, same unit (0 where
        ``nexp == 0``).
    nexp : numpy.ndarray
        float32 (H, W), whole numbers: unsaturated exposures used per photosite.
    quality : numpy.ndarray or None
        uint8 (H, W) bit field of :data:`hdrcap.pipeline.schema.QUALITY_BITS` (0: trusted);
        None when not computed (a baseline weighting).
    sigma_calibration : numpy.ndarray or None
        float32 (H, W), the calibration's part of ``sigma`` (systematic), same unit; None when
        the calibration carries no standard errors (its part is then unknown, not zero).
    header : dict
        JSON-ready description with the keys of :data:`hdrcap.pipeline.schema.HEADER_KEYS`
        (unit, channel meanings, exposure times, files, calibration, options, the merge's
        record under ``"merge"``); written into the EXR.

    Examples
    --------
    >>> import numpy as np
    >>> r = HdrResult(np.ones((2, 2), np.float32), np.full((2, 2), 0.1, np.float32), np.ones((2, 2), np.float32))
    >>> r.shape, list(r.channels())
    ((2, 2), ['irradiance', 'sigma', 'nexp'])
    """

    irradiance: np.ndarray
    sigma: np.ndarray
    nexp: np.ndarray
    quality: np.ndarray | None = None
    sigma_calibration: np.ndarray | None = None
    header: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        """Mosaic size (rows, columns), photosites."""
        h, w = np.shape(self.irradiance)
        return int(h), int(w)

    @property
    def measured(self) -> np.ndarray:
        """Boolean (H, W): photosites with at least one unsaturated exposure."""
        return np.asarray(self.nexp) > 0

    @property
    def info(self) -> dict[str, Any]:
        """The merge's own record (``header["merge"]``): options, dark strategies, counts."""
        return self.header.get("merge") or {}

    def channels(self) -> dict[str, np.ndarray]:
        """The channels present, by name, in the order of
        :data:`hdrcap.pipeline.schema.CHANNEL_NAMES`.

        Returns
        -------
        dict of str to numpy.ndarray
        """
        present = {name: getattr(self, name) for name in CHANNEL_NAMES}
        return {name: arr for name, arr in present.items() if arr is not None}

    def replace(self, **changes: Any) -> HdrResult:
        """A copy with some fields replaced (the arrays are shared, not copied).

        Parameters
        ----------
        **changes
            Fields of :class:`HdrResult`.

        Returns
        -------
        HdrResult
        """
        return dataclasses.replace(self, **changes)

    def write(
        self,
        path: str | os.PathLike[str],
        *,
        force: bool = False,
        compression: str = "zip",
        sigma_precision: str = "auto",
        dng_bits: int = 32,
    ) -> Path:
        """Write this result, atomically: an EXR with every channel and the header, or a
        float CFA DNG of the irradiance when ``path`` ends in ``.dng``
        (:func:`hdrcap.pipeline.io.results.write_result`, which every command uses too).

        Parameters
        ----------
        path : str or path-like
            Output file; its folder must exist.
        force : bool
            Replace an existing file.
        compression : str
            EXR compression: zip (default), zips, piz, zstd, rle or none.
        sigma_precision : {"auto", "half", "float"}
            Storage of the sigma channels.
        dng_bits : {32, 16}
            Float width of a DNG.

        Returns
        -------
        pathlib.Path
            The file written.

        Raises
        ------
        OutputExistsError
            The file exists and ``force`` is false.
        InputError
            The folder does not exist or is not writable; a bad option.
        """
        from hdrcap.pipeline.io.results import write_result

        return write_result(
            self, path, force=force, compression=compression, sigma_precision=sigma_precision, dng_bits=dng_bits
        )


#: Photosites of the regular subsample the median relative sigma is taken over, at most.
MEDIAN_SAMPLES = 1_000_000

#: Rows :func:`summarise` reads at a time (a tiled merge's channels are files).
_SUMMARY_ROWS = 256


def summarise(result: HdrResult) -> dict[str, Any]:
    """Figures of a merge for a one-line report, read in blocks of rows.

    Parameters
    ----------
    result : HdrResult
        The merge.

    Returns
    -------
    dict
        ``shape``; ``irradiance_min``/``max`` (the header's unit); ``median_relative_sigma``
        (over a regular subsample of at most :data:`MEDIAN_SAMPLES` measured photosites);
        ``saturated_everywhere`` (defects and photosites masked in every frame not counted);
        ``defects_flagged``; ``finite`` (everything finite); ``unit``; and, when some frame had
        masked values, ``masked_photosites``.
    """
    from hdrcap.pipeline.io.files import release_mapped_pages

    h, w = result.shape
    step = max(1, h * w // MEDIAN_SAMPLES)
    lo, hi, unused, finite = np.inf, -np.inf, 0, True
    ratios = []
    for r0 in range(0, h, _SUMMARY_ROWS):
        irr, sig, nexp = (
            np.asarray(a[r0 : r0 + _SUMMARY_ROWS]) for a in (result.irradiance, result.sigma, result.nexp)
        )
        # a float array is finite where its least and largest value are (a NaN makes both NaN)
        ext = (irr.min(), irr.max(), sig.min(), sig.max())
        finite = finite and bool(np.isfinite(ext).all())
        lo, hi = min(lo, float(ext[0])), max(hi, float(ext[1]))
        ok = nexp > 0
        unused += ok.size - int(np.count_nonzero(ok))
        pick = np.arange((-r0 * w) % step, irr.size, step)  # flat index a multiple of step
        sel = ok.ravel()[pick]
        ratios.append(sig.ravel()[pick][sel] / np.maximum(np.abs(irr.ravel()[pick][sel]), 1e-30))
        release_mapped_pages([irr, sig, nexp])
    info = result.info
    n_defects = int(info.get("defects_flagged", 0))  # nexp = 0 too, saturated or not
    n_void = int(info.get("masked_everywhere", 0))  # nexp = 0, no information at all
    ratio = np.concatenate(ratios) if ratios else np.empty(0)
    out = {
        "shape": [h, w],
        "irradiance_min": lo,
        "irradiance_max": hi,
        "median_relative_sigma": float(np.median(ratio)) if ratio.size else None,
        "saturated_everywhere": unused - n_defects - n_void,
        "defects_flagged": n_defects,
        "finite": finite,
        "unit": result.header.get("unit"),
    }
    if info.get("masked_photosites"):  # only where a frame had masked values
        out["masked_photosites"] = int(info["masked_photosites"])
    return out
