"""Plan files: the JSON that ``hdrcap plan --json`` writes, read back for a merge or a run.

A plan file lists the planned exposure times (s) with one dark strategy and one master-dark
frame count N per exposure, the planner's decisions and the merge options they imply.
:func:`read_plan` / :func:`check_plan` turn it into a :class:`PlanFile` with one-line errors
naming the file; :func:`apply_plan_options` combines the plan's decided merge options with the
ones a user gave; :func:`planner_attribute` is what an EXR header records of the plan.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hdrcap.pipeline.errors import InputError
from hdrcap.pipeline.noise import DarkStrategy
from hdrcap.pipeline.times import find_exposure

__all__ = [
    "PLAN_OPTIONS",
    "PlanFile",
    "read_plan",
    "check_plan",
    "decided_merge_options",
    "planner_attribute",
    "apply_plan_options",
]

#: Merge options a plan may decide (a user's own value of any of them wins).
PLAN_OPTIONS = ("iterations", "tolerance", "saturation", "saturation_sigmas", "prnu")

#: The near-saturation margin a plan without ``merge_options`` assumed (the merge's default).
_DEFAULT_SATURATION_SIGMAS = 3.0

#: JSON types of the merge options a plan may decide (their ranges are the merge's to check).
_OPTION_TYPES = {
    "iterations": (int,),
    "tolerance": (int, float),
    "saturation": (str,),
    "saturation_sigmas": (int, float),
    "prnu": (str,),
}


@dataclass
class PlanFile:
    """A plan written by ``hdrcap plan --json``, its exposure times grouped by
    :func:`pipeline.times.same_exposure`.

    Attributes
    ----------
    path : str or None
        Where the plan came from (for messages).
    data : dict
        The plan's JSON object.
    sha256 : str or None
        Hash of the file's bytes.
    times : list of float
        Distinct planned exposure times, s.
    strategies : list of DarkStrategy
        Dark strategy of each time.
    n_dark : list of float
        Planned frame count N of each time's master dark (the largest planned).
    counts : list of int
        Planned frames of each time.
    """

    path: str | None
    data: dict
    sha256: str | None
    times: list[float] = field(default_factory=list)
    strategies: list[DarkStrategy] = field(default_factory=list)
    n_dark: list[float] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)

    def group(self, t: float) -> int | None:
        """Index of the planned exposure time that is the same exposure as ``t`` (s), or None."""
        return find_exposure(t, self.times)

    def merge_options(self) -> dict[str, Any]:
        """The merge options the plan decided: its ``merge_options``, or the ones
        :func:`decided_merge_options` derives from its decisions; without the dark
        strategy and N (those are per exposure: :attr:`strategies`, :attr:`n_dark`)."""
        mo = self.data.get("merge_options")
        if mo is None:
            try:
                d = self.data
                mo = decided_merge_options(
                    dict(d.get("decisions") or {}),
                    list(d.get("darks", [])),
                    list(d.get("n_dark") or [1] * len(d.get("darks", []))),
                    _DEFAULT_SATURATION_SIGMAS,
                )
            except (KeyError, TypeError, ValueError, AttributeError) as err:
                raise InputError(
                    f"{self.path}: the plan's decisions are malformed ({type(err).__name__}: {err})"
                ) from None
        if not isinstance(mo, dict):
            raise InputError(f"{self.path}: merge_options must be a JSON object")
        for name, kinds in _OPTION_TYPES.items():
            value = mo.get(name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, kinds)):
                raise InputError(f"{self.path}: merge option {name} = {value!r} is not a {kinds[-1].__name__}")
        return {k: v for k, v in mo.items() if k not in ("dark_strategy", "n_dark")}


def decided_merge_options(
    decisions: dict[str, Any], darks: list[str], n_dark: list[float], saturation_sigmas: float
) -> dict[str, Any]:
    """The merge options a plan's decisions imply (the one mapping, used by the planner when it
    writes a plan and here for a plan file without ``merge_options``).

    Parameters
    ----------
    decisions : dict
        The planner's decisions, name -> {"choice": ..., ...}.
    darks : list of str
        Dark strategy per planned exposure.
    n_dark : list of float
        Planned master-dark frame count per exposure.
    saturation_sigmas : float
        Margin of the near-saturation rule the plan assumed, standard deviations.

    Returns
    -------
    dict
        ``iterations``, ``saturation``, ``saturation_sigmas``, ``prnu`` as decided; and, only
        when every exposure has the same dark strategy, ``dark_strategy`` (plus ``n_dark`` when
        that is "master" with one frame count).

    Examples
    --------
    >>> decided_merge_options({"prnu": {"choice": "scalar"}}, ["model", "model"], [1, 1], 3.0)
    {'saturation_sigmas': 3.0, 'prnu': 'scalar', 'dark_strategy': 'model'}
    """
    out: dict[str, Any] = {}
    if "iterations" in decisions:
        out["iterations"] = int(decisions["iterations"]["choice"])
    if "saturation" in decisions:
        out["saturation"] = decisions["saturation"]["choice"]
    out["saturation_sigmas"] = float(saturation_sigmas)
    if "prnu" in decisions:
        out["prnu"] = decisions["prnu"]["choice"]
    if darks and len(set(darks)) == 1:
        out["dark_strategy"] = darks[0]
        if darks[0] == "master" and len(set(n_dark)) == 1:
            out["n_dark"] = int(n_dark[0])
    return out


def read_plan(path: str | os.PathLike[str]) -> PlanFile:
    """Read and check a plan JSON (``hdrcap plan --json``).

    Parameters
    ----------
    path : str or path
        The plan file.

    Returns
    -------
    PlanFile

    Raises
    ------
    InputError
        Unreadable file, invalid JSON or not a plan; the message names the file.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise InputError(f"{path}: cannot read the plan ({err.strerror or err})") from None
    try:
        d = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise InputError(f"{path}: not a plan (invalid JSON: {err})") from None
    return check_plan(d, str(path), hashlib.sha256(raw).hexdigest())


def _check_exposures(d: dict, where: str) -> tuple[list, list, list]:
    """The plan's exposures (s), dark strategies and master-dark frame counts, checked."""
    exp = d.get("exposures")
    if not isinstance(exp, list) or not exp:
        raise InputError(f"{where}: the plan has no exposures (key 'exposures': a list of seconds)")
    for t in exp:
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not (math.isfinite(t) and t > 0):
            raise InputError(f"{where}: exposure time {t!r} is not a positive number of seconds")
    darks = d.get("darks")
    if not isinstance(darks, list) or len(darks) != len(exp):
        raise InputError(f"{where}: 'darks' must list one dark strategy per exposure ({len(exp)})")
    for s in darks:
        if not isinstance(s, str) or s not in set(DarkStrategy):
            raise InputError(f"{where}: dark strategy {s!r} is not matched, master or model")
    nd = d.get("n_dark")
    if nd is None:
        nd = [1] * len(exp)
    if (
        not isinstance(nd, list)
        or len(nd) != len(exp)
        or not all(isinstance(n, (int, float)) and not isinstance(n, bool) and n >= 0 for n in nd)
    ):
        raise InputError(f"{where}: 'n_dark' must list one frame count >= 0 per exposure ({len(exp)})")
    return exp, [DarkStrategy(s) for s in darks], nd


def check_plan(d: object, where: str | None = None, sha256: str | None = None) -> PlanFile:
    """A :class:`PlanFile` from a plan's JSON object.

    Parameters
    ----------
    d : object
        The parsed JSON.
    where : str, optional
        Name for messages (the file; default ``"plan"``).
    sha256 : str, optional
        Hash of the file's bytes, kept in the result.

    Returns
    -------
    PlanFile

    Raises
    ------
    InputError
        One line naming ``where``: missing or malformed exposures, dark strategies, frame
        counts, decisions or merge options; one exposure planned with two dark strategies.
    """
    where = where or "plan"
    if not isinstance(d, dict):
        raise InputError(f"{where}: not a plan (expected a JSON object from `hdrcap plan --json`)")
    exp, darks, nd = _check_exposures(d, where)
    for key in ("decisions", "merge_options"):
        if d.get(key) is not None and not isinstance(d[key], dict):
            raise InputError(f"{where}: {key!r} must be a JSON object")
    plan = PlanFile(where, d, sha256)
    for t, s, n in zip(exp, darks, nd):
        i = plan.group(float(t))
        if i is None:
            plan.times.append(float(t))
            plan.strategies.append(s)
            plan.n_dark.append(float(n))
            plan.counts.append(1)
        elif plan.strategies[i] is not s:
            raise InputError(
                f"{where}: exposure {t:g} s is planned with two dark strategies ({plan.strategies[i]} and {s})"
            )
        else:
            plan.counts[i] += 1
            plan.n_dark[i] = max(plan.n_dark[i], float(n))
    return plan


def planner_attribute(
    plan: dict,
    plan_file: str | None = None,
    sha256: str | None = None,
    from_plan: dict | None = None,
    overridden: dict | None = None,
    **more: Any,
) -> dict:
    """The ``planner`` attribute of the EXR header.

    Parameters
    ----------
    plan : dict
        The plan's JSON object.
    plan_file, sha256 : str, optional
        The plan's file and the hash of its bytes.
    from_plan : dict, optional
        Merge options taken from the plan.
    overridden : dict, optional
        Options the user overrode: name -> {"plan", "used"}.
    **more
        Further entries.

    Returns
    -------
    dict
        The plan's decisions, predicted minimum SNR (dB), target, total time (s), exposures
        and dark strategies, file and hash, and which options came from it.
    """
    return {
        "plan_file": plan_file,
        "plan_sha256": sha256,
        "decisions": plan.get("decisions") or {},
        "predicted_min_snr_db": plan.get("predicted_min_snr_db"),
        "target_snr_db": plan.get("target_snr_db"),
        "total_time_s": plan.get("total_time_s"),
        "feasible": plan.get("feasible"),
        "exposures": plan.get("exposures"),
        "darks": plan.get("darks"),
        "n_dark": plan.get("n_dark"),
        "options_from_plan": dict(from_plan or {}),
        "options_overridden": dict(overridden or {}),
        **more,
    }


def apply_plan_options(plan: PlanFile, options: dict, given: Callable[[str], bool]) -> tuple[dict, dict, dict, list]:
    """Combine merge ``options`` (a user's) with the plan's decided options.

    Parameters
    ----------
    plan : PlanFile
    options : dict
        Merge options (fields of :class:`pipeline.merge.accumulator.MergeOptions`).
    given : callable
        ``given(name)``: whether the user set option ``name`` (then it wins).

    Returns
    -------
    tuple
        (options, options taken from the plan, options overridden as name -> {"plan",
        "used"}, names of decided options a merge does not know).
    """
    decided = plan.merge_options()
    options, taken, overridden = dict(options), {}, {}
    ignored = sorted(set(decided) - set(PLAN_OPTIONS))
    for name in PLAN_OPTIONS:
        if name not in decided:
            continue
        value = decided[name]
        if given(name):
            if options.get(name) != value:
                overridden[name] = {"plan": value, "used": options.get(name)}
        else:
            options[name] = value
            taken[name] = value
    return options, taken, overridden, ignored
