"""A static gallery of the sub-goals found by curiosity-driven discovery (CSD, section 4.2).

:func:`write_gallery` writes a self-contained HTML page (images embedded as base64 PNG) and a PNG
contact sheet. From a saved model: ``python -m sb3_hhp.gallery MODEL [--out DIR]``.

Each record is a dict: ``id`` (int), ``image`` (RGB uint8 array), ``found_at`` (env step),
``success_rate`` (its subpolicy's, in [0, 1], or ``None``), ``chosen_recently`` (how often the
meta-controller chose it lately), ``mean_score`` (the preference predictor's mean score, or ``None``).
"""

import argparse
import base64
import html
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from sb3_hhp.preferences.codecs import encode_png

__all__ = ["main", "write_gallery"]

HTML_NAME = "subgoals.html"
SHEET_NAME = "subgoals.png"
#: what each figure under a sub-goal means, shown above the gallery
LEGEND = (
    ("name", "the situation the sub-goal stands for, in words; the image is the state where it was found"),
    ("found at step", "the environment step at which curiosity-driven discovery added it"),
    ("success", "share of its last 100 tries in which its subpolicy reached it"),
    ("chosen", "how often the meta-controller chose it in its last 1,000 choices"),
    (
        "score",
        "the preference predictor's mean score for it over the states of the latest episode: higher means people "
        "are predicted to prefer it; compare it between sub-goals (it has no fixed scale)",
    ),
)


def _fmt(value: Optional[float], digits: int, percent: bool = False) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{100 * value:.0f} %" if percent else f"{value:.{digits}f}"


def _caption(record: dict) -> tuple[str, str]:
    found_at = record.get("found_at")
    first = f"#{int(record['id'])}  found at step {'–' if found_at is None else int(found_at)}"
    if record.get("name"):
        first = f"{first}\n{record['name']}"
    second = (
        f"success {_fmt(record.get('success_rate'), 0, percent=True)}  chosen {int(record.get('chosen_recently') or 0)}"
        f"  score {_fmt(record.get('mean_score'), 3)}"
    )
    return first, second


def _check_records(records: Sequence[dict]) -> list[dict]:
    checked = []
    for index, record in enumerate(records):
        if not isinstance(record, dict) or "id" not in record or "image" not in record:
            raise ValueError(f"Sub-goal record {index} must be a dict with at least 'id' and 'image'")
        image = np.asarray(record["image"])
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise ValueError(
                f"Sub-goal {record['id']}'s image must be a uint8 (H, W) or (H, W, 3) array, "
                f"got dtype {image.dtype} shape {image.shape}"
            )
        checked.append({**record, "image": image})
    return sorted(checked, key=lambda record: int(record["id"]))


def _write_html(records: list[dict], path: Path, title: str) -> None:
    cards = []
    for record in records:
        png = base64.b64encode(encode_png(record["image"], f"sub-goal {record['id']}'s image")).decode("ascii")
        first, second = _caption(record)
        cards.append(
            f'<figure data-subgoal-id="{int(record["id"])}"><img alt="sub-goal {int(record["id"])}" '
            f'src="data:image/png;base64,{png}"><figcaption><b>{html.escape(first)}</b><br>'
            f"{html.escape(second)}</figcaption></figure>"
        )
    body = "\n".join(cards) if cards else "<p>No sub-goal yet.</p>"
    legend = "".join(f"<dt>{html.escape(term)}</dt><dd>{html.escape(text)}</dd>" for term, text in LEGEND)
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font: 15px/1.4 system-ui, sans-serif; margin: 1rem; background: #f6f6f3; }}
.grid {{ display: grid; grid-template-columns: repeat(auto-fill, minmax(280px, 1fr)); gap: 1rem; }}
figure {{ margin: 0; background: #fff; border: 1px solid #d6d6d0; border-radius: 6px; padding: 0.6rem; }}
img {{ display: block; width: 256px; height: 256px; object-fit: contain; image-rendering: pixelated;
       background: #222; margin: 0 auto; }}
figcaption {{ margin-top: 0.4rem; white-space: pre-line; }}
dl {{ display: grid; grid-template-columns: max-content 1fr; gap: 0.15rem 0.8rem; color: #6b6b66; }}
dt {{ font-weight: 600; color: #1d1d1b; }} dd {{ margin: 0; }}
</style></head>
<body><h1>{html.escape(title)} ({len(records)})</h1>
<dl class="legend">{legend}</dl>
<div class="grid">
{body}
</div></body></html>
"""
    path.write_text(page, encoding="utf-8")


def _write_sheet(records: list[dict], path: Path, title: str) -> None:
    # The object-oriented matplotlib API: no pyplot state, no display needed.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n_cols = max(1, math.ceil(math.sqrt(len(records))))
    n_rows = max(1, math.ceil(len(records) / n_cols))
    figure = Figure(figsize=(3.0 * n_cols, 3.4 * n_rows + 0.4))
    FigureCanvasAgg(figure)
    figure.suptitle(f"{title} ({len(records)})")
    axes = figure.subplots(n_rows, n_cols, squeeze=False)
    for index, axis in enumerate(axes.flat):
        axis.set_axis_off()
        if index < len(records):
            record = records[index]
            image = record["image"]
            axis.imshow(image, cmap="gray" if image.ndim == 2 else None, interpolation="nearest")
            axis.set_title("\n".join(_caption(record)), fontsize=8)
    if not records:
        axes[0, 0].text(0.5, 0.5, "No sub-goal yet", ha="center", va="center")
    figure.tight_layout()
    figure.savefig(path, dpi=100)


def write_gallery(
    records: Sequence[dict], out_dir: Union[str, os.PathLike], title: str = "Sub-goals"
) -> tuple[Path, Path]:
    """Write the sub-goal gallery as a static HTML page and a PNG contact sheet.

    :param records: one dict per sub-goal (see the module docstring); shown in order of id
    :param out_dir: folder to write into (created when missing)
    :param title: the page's and sheet's heading
    :return: the paths of the HTML page and of the contact sheet
    """
    checked = _check_records(records)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    html_path, sheet_path = out / HTML_NAME, out / SHEET_NAME
    _write_html(checked, html_path, title)
    _write_sheet(checked, sheet_path, title)
    return html_path, sheet_path


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m sb3_hhp.gallery MODEL [--out DIR]``: write the gallery of a saved HhP model."""
    parser = argparse.ArgumentParser(
        prog="python -m sb3_hhp.gallery", description="Write the sub-goal gallery (HTML + PNG) of a saved HhP model."
    )
    parser.add_argument("model", help="the saved model (the .zip written by HhP.save; the suffix may be left out)")
    parser.add_argument("--out", default=None, help="output folder (default: <model>_gallery beside the model)")
    args = parser.parse_args(argv)
    model_path = args.model
    if not os.path.isfile(model_path) and os.path.isfile(model_path + ".zip"):
        model_path += ".zip"
    if not os.path.isfile(model_path):
        print(f"error: no saved model at {args.model!r} (nor {args.model + '.zip'!r})", file=sys.stderr)
        return 2
    out_dir = args.out or os.path.splitext(model_path)[0] + "_gallery"
    try:
        from sb3_hhp import HhP

        model: Any = HhP.load(model_path)
        records = model.subgoal_records()
    except Exception as error:  # report any loading failure as a clear message, not a traceback
        print(f"error: cannot load the HhP model {model_path!r}: {type(error).__name__}: {error}", file=sys.stderr)
        return 1
    html_path, sheet_path = write_gallery(records, out_dir)
    print(f"{len(records)} sub-goals: {html_path} and {sheet_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
