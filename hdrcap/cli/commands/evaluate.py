"""``hdrcap evaluate``: the paper's Sec. 7 on the simulated cameras (Table 2), and Fig. 8d.

The experiments are :mod:`hdrcap.experiments`; this command parses the options and prints
the summary.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from hdrcap.pipeline.errors import InputError

__all__ = ["command"]


def _print_summary(results: dict[str, Any]) -> None:
    for label, rows in results["summary"].items():
        click.echo(f"{label}: mean efficiency (bound/MSE) and mean SNR - optimal (dB) per method")
        for name, row in rows.items():
            d = row.get("mean_snr_minus_optimal_db")
            click.echo(
                f"  {name:18s} eff {row['mean_efficiency']:.3f} (min {row['min_efficiency']:.3f})"
                + (f"  {d:+.2f} dB" if d is not None else "")
            )
    for label, d in results["qq"].items():
        rates = ", ".join(f"{k} {v['test']['rejection_rate']:.0%}" for k, v in d["levels"].items())
        click.echo(f"Gaussian check {label}: Shapiro-Wilk rejection at 5 %: {rates}")


@click.command(
    "evaluate", short_help="Reproduce the paper's Sec. 7 evaluation: SNR per weighting vs the bound, Q-Q, efficiency."
)
@click.option(
    "--out",
    type=click.Path(file_okay=False, path_type=Path),
    required=True,
    help="Output folder for evaluation.json and the PNG plots.",
)
@click.option("--quick", is_flag=True, help="Smaller images and fewer repetitions (about 4x faster).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--denoise", is_flag=True, help="Also run the denoising experiment (Sec. 9, Fig. 8d).")
@click.option("--force", is_flag=True, help="Overwrite existing outputs.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as one line of JSON.")
def command(out: Path, quick: bool, seed: int, denoise: bool, force: bool, as_json: bool) -> None:
    """Reproduce the paper's evaluation (Sec. 7) on simulated camera-A and camera-B.

    Writes evaluation.json (every number) and fig2_weights.png, fig4_snr.png,
    fig5_readout.png, fig6_qq.png and efficiency.png into OUT: SNR against irradiance of
    every Table 1 weighting and of the maximum-likelihood merge with the Cramér-Rao bound,
    the zero and 10x readout-noise cases, weights against output value, normal Q-Q plots
    and the efficiency (bound / MSE) per irradiance bin.
    """
    from hdrcap.cli.util import echo_json
    from hdrcap.experiments import evaluate_denoising, run_evaluation
    from hdrcap.pipeline.io.files import check_new_output

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    for name in ("evaluation.json", "fig4_snr.png"):
        check_new_output(out / name, force)
    say = None if as_json else (lambda msg: click.echo(msg, err=True))
    results = run_evaluation(out, quick=quick, seed=seed, force=force, progress=say)
    summary = {"out": str(out), "plots": results["plots"], "seconds": results["seconds"], "summary": results["summary"]}
    if denoise:
        summary["denoise"] = evaluate_denoising(out, seed=seed, quick=quick)
    if as_json:
        echo_json(summary)
    else:
        _print_summary(results)
        click.echo(f"wrote {out / 'evaluation.json'} and {', '.join(results['plots'])} in {results['seconds']:.1f} s")
