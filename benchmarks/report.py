"""Report a sweep of ``python -m benchmarks.run``: a Markdown table and one learning-curve plot per env.

    python benchmarks/report.py benchmarks/results/doorkey8x8/results.csv
    python benchmarks/report.py            # every benchmarks/results/*/results.csv

Next to each ``results.csv`` it writes ``benchmark.md`` (one row per env x variant: mean ± std over seeds of
the success rate of the deterministic and of the stochastic policy on the fresh evaluation episodes, of the
labels used and of the wall time) and ``curves_<env>.png`` (success rate at the periodic evaluations against
env steps: the mean over seeds, a band of ± one std, a line per variant), and prints the table. Runs started but
without a row yet (still training, or stopped) are listed apart with the steps their periodic evaluations reached,
and drawn as dashed lines from those evaluations (``curves/<run>.partial.csv``): a sweep of runs that take hours can
be looked at while it runs, and a stopped run's evaluations are not lost.
Needs the ``plots`` extra (pandas, matplotlib).
"""

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd

try:
    from benchmarks.run import Experiment, _curve_from_evaluations, attempt_evaluations
except ImportError:  # run as a script, python benchmarks/report.py: the repository's root is not on the path
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from benchmarks.run import Experiment, _curve_from_evaluations, attempt_evaluations

#: variant -> name in tables and legends, in the order of tables and plots
VARIANT_NAMES = {"hhp": "HhP", "dqn": "DQN", "ppo": "PPO", "ppo_rnd": "PPO + RND"}
#: columns a results file must have
REQUIRED_COLUMNS = ("env", "variant", "seed", "steps", "success_det", "success_stoch", "labels_used", "wall_seconds")
#: points of the common step grid the seeds' curves are interpolated onto
CURVE_GRID_POINTS = 100


def variant_name(variant: str) -> str:
    """A variant's name in tables and legends; a sweep's own HhP variants read "HhP, <the rest>" (``hhp_rho0.2``:
    "HhP, rho0.2"; ``hhp_no_curiosity``: "HhP, no curiosity")."""
    if variant in VARIANT_NAMES:
        return VARIANT_NAMES[variant]
    return "HhP, " + variant[len("hhp_"):].replace("_", " ") if variant.startswith("hhp_") else variant


def _variant_order(variants: Sequence[str]) -> list[str]:
    known = [variant for variant in VARIANT_NAMES if variant in set(variants)]
    return known + sorted(set(variants) - set(known))


def read_results(csv_path: Path) -> pd.DataFrame:
    """A sweep's ``results.csv``, checked for the columns the report reads."""
    if not csv_path.is_file():
        raise SystemExit(f"No results file {csv_path}: run python -m benchmarks.run CONFIG first (or pass its results.csv)")
    results = pd.read_csv(csv_path)
    missing = [column for column in REQUIRED_COLUMNS if column not in results.columns]
    if missing:
        raise SystemExit(f"{csv_path} lacks the columns {', '.join(missing)}: not written by python -m benchmarks.run")
    return results


def _mean_std(values: pd.Series, digits: int = 2, scale: float = 1.0) -> str:
    """``mean ± std`` (sample std over seeds; the mean alone for one seed; "–" when there is no value)."""
    values = values.dropna().astype(float) / scale
    if values.empty:
        return "–"
    if len(values) == 1:
        return f"{values.iloc[0]:.{digits}f}"
    return f"{values.mean():.{digits}f} ± {values.std(ddof=1):.{digits}f}"


def _time_unit(seconds: pd.Series) -> tuple[str, float]:
    longest = float(seconds.max()) if len(seconds.dropna()) else 0.0
    if longest < 600:
        return "s", 1.0
    if longest < 36_000:
        return "min", 60.0
    return "h", 3600.0


def markdown_table(results: pd.DataFrame) -> str:
    """One row per env x variant: seeds, steps, success (deterministic, stochastic), labels used, wall time.

    :param results: the rows of ``results.csv``
    :return: the table in Markdown (GitHub's pipe tables)
    """
    unit, scale = _time_unit(results["wall_seconds"])
    header = [
        "env", "variant", "seeds", "steps", "success (deterministic)", "success (stochastic)", "labels used",
        f"wall time ({unit})",
    ]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([" --- "] * 2 + [" ---: "] * (len(header) - 2)) + "|"]
    for env in sorted(results["env"].unique()):
        rows = results[results["env"] == env]
        for variant in _variant_order(list(rows["variant"].unique())):
            runs = rows[rows["variant"] == variant]
            steps = sorted(int(value) for value in runs["steps"].unique())
            cells = [
                env,
                variant_name(variant),
                str(runs["seed"].nunique()),
                " / ".join(f"{value:,}" for value in steps),
                _mean_std(runs["success_det"]),
                _mean_std(runs["success_stoch"]),
                _mean_std(runs["labels_used"], digits=0),
                _mean_std(runs["wall_seconds"], digits=1 if unit != "s" else 0, scale=scale),
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def mean_curve(curves: Sequence[pd.DataFrame], column: str = "success") -> Optional[pd.DataFrame]:
    """The seeds' curves on one step grid (linear interpolation, within the steps every seed covers): mean, std.

    :param curves: one DataFrame per seed, with ``steps`` and ``column``
    :param column: the value to average
    :return: ``steps``, ``mean``, ``std`` (0 for a single seed), or None without points
    """
    curves = [curve.sort_values("steps") for curve in curves if len(curve)]
    if not curves:
        return None
    if len(curves) == 1:
        curve = curves[0]
        return pd.DataFrame({"steps": curve["steps"], "mean": curve[column], "std": 0.0})
    low = max(float(curve["steps"].iloc[0]) for curve in curves)
    high = min(float(curve["steps"].iloc[-1]) for curve in curves)
    if high < low:
        return None
    grid = np.linspace(low, high, CURVE_GRID_POINTS) if high > low else np.array([low])
    values = np.stack([np.interp(grid, curve["steps"], curve[column]) for curve in curves])
    return pd.DataFrame({"steps": grid, "mean": values.mean(axis=0), "std": values.std(axis=0, ddof=1)})


def unfinished_runs(results: pd.DataFrame, folder: Path) -> pd.DataFrame:
    """The runs with a log folder (``logs/<run>``) and no row in ``results``: still training, or stopped. The newest
    periodic evaluations under each log folder (every part of a resumed run) become ``curves/<run>.partial.csv``; a
    finished run's partial curve, written while it ran, is removed (its row's curve replaces it).

    :return: one row per run: ``env`` (as in run names: ``/`` written ``-``), ``variant``, ``seed``, ``steps`` (the
        last periodic evaluation's, 0 before any), ``success`` (at that evaluation), ``curve`` (relative to ``folder``)
    """
    finished = {Experiment(row.env, row.variant, int(row.seed), int(row.steps)).name for row in results.itertuples()}
    rows = []
    for log in sorted((folder / "logs").glob("*__*__s*")):
        if not log.is_dir():
            continue
        relative = Path("curves") / f"{log.name}.partial.csv"
        if log.name in finished:
            (folder / relative).unlink(missing_ok=True)
            continue
        env, variant, seed = log.name.rsplit("__", 2)
        written = _curve_from_evaluations(attempt_evaluations(log), folder / relative)
        curve = pd.read_csv(folder / relative) if written else None
        rows.append({"env": env, "variant": variant, "seed": int(seed[1:]),
                     "steps": int(curve["steps"].iloc[-1]) if curve is not None else 0,
                     "success": float(curve["success"].iloc[-1]) if curve is not None else float("nan"),
                     "curve": str(relative) if written else None})
    return pd.DataFrame(rows, columns=["env", "variant", "seed", "steps", "success", "curve"])


def unfinished_table(unfinished: pd.DataFrame) -> str:
    """The unfinished runs in Markdown (empty without any)."""
    if unfinished.empty:
        return ""
    lines = ["| run | steps reached | success at the last periodic evaluation |", "| --- | ---: | ---: |"]
    for row in unfinished.itertuples():
        success = "–" if np.isnan(row.success) else f"{row.success:.2f}"
        lines.append(f"| {row.env} {variant_name(row.variant)} seed {row.seed} | {row.steps:,} | {success} |")
    return "\n".join(lines) + "\n"


def plot_curves(results: pd.DataFrame, folder: Path, unfinished: Optional[pd.DataFrame] = None) -> list[Path]:
    """One plot per env with learning curves: success rate against env steps, mean ± std over seeds per variant;
    each unfinished run (:func:`unfinished_runs`) a dashed line of its own.

    :param results: the rows of ``results.csv`` (``curve``: a path relative to ``folder``, or empty)
    :param folder: the folder of ``results.csv``, where the plots go
    :param unfinished: runs without a row yet, with their partial curves
    :return: the plots written
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    if "curve" not in results.columns:
        return written
    unfinished = unfinished if unfinished is not None else pd.DataFrame(columns=["env", "variant", "seed", "steps", "curve"])
    unfinished = unfinished[unfinished["curve"].notna()]
    # envs by their names in run names ('/' written '-'), titled with their ids where a finished run gives one
    titles = {env.replace("/", "-"): env for env in results["env"].unique()}
    titles.update({env: titles.get(env, env) for env in unfinished["env"].unique()})
    for name in sorted(titles):
        env = titles[name]
        rows = results[(results["env"] == env) & results["curve"].notna()]
        partial = unfinished[unfinished["env"] == name]
        if rows.empty and partial.empty:
            continue
        fig, ax = plt.subplots(figsize=(6, 4))
        for variant in _variant_order(list(rows["variant"].unique())):
            paths = [folder / path for path in rows[rows["variant"] == variant]["curve"]]
            curves = [pd.read_csv(path) for path in paths if path.is_file()]
            curve = mean_curve(curves)
            if curve is None:
                continue
            label = f"{variant_name(variant)} ({len(curves)} seed{'s' if len(curves) > 1 else ''})"
            (line,) = ax.plot(curve["steps"], curve["mean"], label=label)
            ax.fill_between(
                curve["steps"], (curve["mean"] - curve["std"]).clip(0, 1), (curve["mean"] + curve["std"]).clip(0, 1),
                color=line.get_color(), alpha=0.2, linewidth=0,
            )
        for row in partial.itertuples():
            curve = pd.read_csv(folder / row.curve)
            ax.plot(curve["steps"], curve["success"], linestyle="--", marker=".",
                    label=f"{variant_name(row.variant)} seed {row.seed} (unfinished, {row.steps:,} steps)")
        ax.set_title(env)
        ax.set_xlabel("env steps")
        ax.set_ylabel("success rate (periodic evaluations)")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = folder / f"curves_{env.replace('/', '-')}.png"
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)
    return written


def greedy_rows(results: pd.DataFrame, folder: Path, key: str = "break_cycles") -> list[tuple[int, str, str]]:
    """The HhP runs whose deterministic figure is plain greedy: their summary (``runs/<run>.json``) predates
    ``break_cycles`` or says it was off (``key="stochastic_breaks_cycles"``: whose stochastic figure is plain
    epsilon-greedy). Rows of other variants, or without a summary, are not named.

    :return: per such run: its row's index in ``results``, its name in the tables, its run name (its log folder's)
    """
    named = []
    for index, row in zip(results.index, results.itertuples(index=False)):
        summary = getattr(row, "summary", None)
        if not str(row.variant).startswith("hhp") or not isinstance(summary, str) or not (folder / summary).is_file():
            continue
        if not json.loads((folder / summary).read_text()).get(key, False):
            run = Experiment(row.env, row.variant, int(row.seed), int(row.steps)).name
            named.append((index, f"{row.env} {variant_name(str(row.variant))} seed {int(row.seed)}", run))
    return named


def reevaluations(folder: Path) -> list[dict]:
    """The figures of models that ``benchmarks/evaluate.py`` evaluated again with cycles broken: the JSON files it wrote
    into ``folder`` (``{"env", "episodes", "runs": [...]}``, or the rows under ``"variants"``). A figure counts where
    its row records ``break_cycles`` true, or, in files written before rows recorded it, where no load option turned
    it off (models saved before ``break_cycles`` existed load with it on); files in order of name.

    :return: each figure's ``success`` (deterministic), ``episodes``, ``file`` (its name) and ``folders`` (those of its
        model's path: a run's log folder is named as the run)
    """
    found: list[dict] = []
    for path in sorted(folder.glob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if not isinstance(data, dict):
            continue
        rows = data.get("runs")
        if rows is None and isinstance(data.get("variants"), dict):  # one list per variant
            rows = [row for variant in data["variants"].values() if isinstance(variant, list) for row in variant]
        for row in rows if isinstance(rows, list) else []:
            if not isinstance(row, dict) or "deterministic" not in row:
                continue
            options = row.get("load_options") or {}
            if not row.get("break_cycles", options.get("break_cycles", True)):
                continue
            found.append({"success": float(row["deterministic"]), "episodes": data.get("episodes"), "file": path.name,
                          "folders": set(Path(str(row.get("model", ""))).parts)})
    return found


def break_cycles_note(results: pd.DataFrame, folder: Path) -> tuple[pd.DataFrame, str]:
    """The rows with the deterministic figures of plain greedy HhP runs replaced by their :func:`reevaluations` on the
    same episodes (as many, the same seeds), and the note under the table that says which and what they were, and
    which runs' stochastic figures are plain epsilon-greedy."""
    greedy, epsilon_greedy = greedy_rows(results, folder), greedy_rows(results, folder, "stochastic_breaks_cycles")
    if not greedy and not epsilon_greedy:
        return results, ""
    again = reevaluations(folder)
    results = results.copy()
    replaced, kept = [], []
    for index, name, run in greedy:
        episodes = results.loc[index, "eval_episodes"] if "eval_episodes" in results else None
        same = [figure for figure in again if run in figure["folders"] and (
            episodes is None or pd.isna(episodes) or figure["episodes"] is None or int(figure["episodes"]) == int(episodes))]
        if not same:  # never evaluated again, or on other episodes than the runner's
            kept.append(name)
            continue
        figure = same[0]
        plain = float(results.loc[index, "success_det"])
        results.loc[index, "success_det"] = figure["success"]
        replaced.append(f"{name} ({figure['success']:.2f}; plain greedy {plain:.2f}; `{figure['file']}`)")
    note = "\nHhP's deterministic policy breaks its cycles (`break_cycles`, the default)."
    if replaced:
        note += (" These runs were evaluated plain greedy by the runner, before it existed, and again with it on the "
                 "same episodes by `benchmarks/evaluate.py`, whose figures the table shows: " + "; ".join(replaced) + ".")
    if kept:
        note += (" These runs were evaluated plain greedy only (their models not evaluated again), and the table shows "
                 "that: " + "; ".join(kept) + ".")
    if epsilon_greedy:
        note += (" The stochastic policy breaks its cycles too (epsilon-greedy around them); these runs' stochastic "
                 "figures are plain epsilon-greedy, evaluated before it did: "
                 + "; ".join(name for _, name, _ in epsilon_greedy) + ".")
    return results, note + "\n"


def report(csv_path: Path) -> tuple[str, Path, list[Path]]:
    """Write ``benchmark.md`` and the plots next to ``csv_path``.

    :return: the table, the Markdown file and the plots
    """
    if csv_path.is_file() or not (csv_path.parent / "logs").is_dir():
        results = read_results(csv_path)
    else:  # a sweep whose runs are all still training
        results = pd.DataFrame(columns=[*REQUIRED_COLUMNS, "curve", "eval_episodes"])
    results, cycles_note = break_cycles_note(results, csv_path.parent)
    table = markdown_table(results)
    episodes = sorted(int(value) for value in results["eval_episodes"].dropna().unique()) if "eval_episodes" in results else []
    note = (
        f"Mean ± std over seeds. Success: fraction of {' / '.join(map(str, episodes)) or 'the'} fresh evaluation "
        "episodes (seeds seed + 10000, ...) solved by the deterministic and by the stochastic policy. Labels: "
        "preference queries answered (HhP only). Wall time: training and evaluation of one run.\n"
    )
    note += cycles_note
    markdown = csv_path.parent / "benchmark.md"
    unfinished = unfinished_runs(results, csv_path.parent)
    plots = plot_curves(results, csv_path.parent, unfinished)
    figures = "".join(f"\n![{path.stem}]({path.name})\n" for path in plots)
    pending = unfinished_table(unfinished)
    if pending:
        pending = ("\nRuns without a final evaluation (still training or stopped; dashed in the plots, from their "
                   f"periodic evaluations):\n\n{pending}")
        table = table + pending
    markdown.write_text(f"# Results of {csv_path.parent.name}\n\n{table}\n{note}{figures}")
    return table, markdown, plots


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "results", nargs="*", help="results.csv files (or their folders); default: every benchmarks/results/*/results.csv"
    )
    args = parser.parse_args(argv)
    paths = [Path(path) for path in args.results]
    paths = [path / "results.csv" if path.is_dir() else path for path in paths]
    if not paths:
        paths = sorted((Path(__file__).resolve().parent / "results").glob("*/results.csv"))
        if not paths:
            print("No benchmarks/results/*/results.csv yet: run python -m benchmarks.run CONFIG first", file=sys.stderr)
            return 1
    for path in paths:
        table, markdown, plots = report(path)
        print(table)
        print(f"Written: {markdown}" + "".join(f", {plot}" for plot in plots))
    return 0


if __name__ == "__main__":
    sys.exit(main())
