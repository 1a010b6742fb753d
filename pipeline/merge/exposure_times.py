"""The exposure times a merge uses: nominal, the calibration's shutter table, the bracket's estimate.

With ``exposure_times="effective"`` (:class:`pipeline.merge.options.MergeOptions`) each frame
starts from its nominal time times the calibration's shutter-table factor
(:class:`pipeline.params.ShutterTable`) as it is added; before the iterations the bracket's own
estimate (:func:`pipeline.exposure_ratio.estimate_exposure_ratios`, Sec. 7) refines the ratios
of the frames that share well-exposed photosites. :class:`ExposureTimes` does both for one
merge and writes the header entries that record them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hdrcap.pipeline.exposure_ratio import ExposureRatios, estimate_exposure_ratios
from hdrcap.pipeline.merge.frames import FrameBook
from hdrcap.pipeline.merge.kernel_inputs import CalibrationMaps
from hdrcap.pipeline.params import Calibration

__all__ = ["ExposureTimes"]


class ExposureTimes:
    """The exposure-time corrections of one merge.

    Parameters
    ----------
    calibration : Calibration
        Camera model (its ``shutter`` table, if any).
    mode : {"nominal", "effective"}
        The merge's ``exposure_times`` option: ``nominal`` applies neither correction.
    """

    def __init__(self, calibration: Calibration, mode: str) -> None:
        self.calibration = calibration
        self.mode = mode
        self.ratios: ExposureRatios | None = None  # the bracket's estimate, once made

    def shutter_corrected(self, t: float) -> tuple[float, bool]:
        """The exposure time a frame of nominal time ``t`` starts from.

        Parameters
        ----------
        t : float
            Nominal exposure time, s.

        Returns
        -------
        (float, bool)
            ``t`` times the calibration's shutter-table factor for ``t`` (s) with
            ``exposure_times="effective"`` when the table has ``t``, else ``t``; and whether
            the table applied.
        """
        table = self.calibration.shutter
        if self.mode != "effective" or table is None:
            return t, False
        hit = table.lookup(t)
        return (t, False) if hit is None else (t * hit[0], True)

    def estimate(self, book: FrameBook, window: Any, maps: CalibrationMaps) -> ExposureRatios:
        """Estimate every frame's effective exposure time from the frames held on the
        photosites ``window`` and make the book use it (x_i of Eq. 6 and the dark current's
        t g coefficient).

        Parameters
        ----------
        book : FrameBook
            The frames (at least two); their times and dark-current coefficients are replaced.
        window : tuple
            A numpy index of the image: the photosites the estimate reads.
        maps : CalibrationMaps
            The merge's maps (the dark levels of the ``model`` and master-dark frames).

        Returns
        -------
        ExposureRatios
            The estimate (also kept as :attr:`ratios`).
        """
        p = self.calibration.params
        dm = self.calibration.defect_map
        ratios = estimate_exposure_ratios(
            [v[window] for v in book.values],
            [book.level_at(i, window, maps.bias, maps.dark_current) for i in range(len(book))],
            book.times,
            float(p.g),
            float(p.sigma2_R),
            float(p.v_sat),
            dark_factors=book.ks,
            exclude=None if dm is None else np.asarray(dm)[window] != 0,
        )
        book.retime(ratios.effective, float(p.g))
        self.ratios = ratios
        return ratios

    def info(self, book: FrameBook) -> dict[str, Any]:
        """The header entries of the exposure times.

        Parameters
        ----------
        book : FrameBook
            The frames merged.

        Returns
        -------
        dict
            ``exposure_times_nominal`` (s), ``exposure_times_calibrated`` (after the shutter
            table, s), ``shutter_table`` (which frames it corrected, its reference time and
            source) and ``exposure_time_ratios`` (the bracket's estimate: factors relative to
            the calibrated times, or None).
        """
        ratios = self.ratios
        table = self.calibration.shutter
        applied = any(book.table)
        return {
            "exposure_times_nominal": list(book.nominal),
            "exposure_times_calibrated": list(ratios.nominal) if ratios is not None else list(book.times),
            "shutter_table": {
                "applied": list(book.table),
                "reference": None if table is None else table.reference,
                "source": "calibration" if applied else None,
            },
            "exposure_time_ratios": None if ratios is None else ratios.to_dict(),
        }
