import base64
import re
import subprocess
import sys

import numpy as np
import pytest
from matplotlib.image import imread

from sb3_hhp.gallery import main, write_gallery
from sb3_hhp.preferences.codecs import decode_png


def records(n: int) -> list[dict]:
    rng = np.random.default_rng(0)
    return [
        {
            "id": i,
            "image": rng.integers(0, 255, (10 + i, 12, 3), dtype=np.uint8),
            "found_at": 1000 * i,
            "success_rate": None if i == 0 else i / 10,
            "chosen_recently": 2 * i,
            "mean_score": None if i == 0 else -0.5 + i,
        }
        for i in reversed(range(n))
    ]


def test_write_gallery_embeds_every_image_with_its_statistics(tmp_path):
    given = records(5)
    html_path, sheet_path = write_gallery(given, tmp_path / "out")
    page = html_path.read_text()
    assert "<script" not in page and "http" not in page  # self-contained
    embedded = re.findall(r'data-subgoal-id="(\d+)"><img alt="[^"]*" src="data:image/png;base64,([^"]+)"', page)
    assert [int(i) for i, _ in embedded] == [0, 1, 2, 3, 4]  # ordered by id
    by_id = {record["id"]: record for record in given}
    for subgoal_id, data in embedded:
        np.testing.assert_array_equal(decode_png(base64.b64decode(data)), by_id[int(subgoal_id)]["image"])
    assert "#3  found at step 3000" in page and "success 30 %  chosen 6  score 2.500" in page
    assert "success –  chosen 0  score –" in page  # sub-goal 0 has no statistics yet

    sheet = imread(sheet_path)
    assert sheet.ndim == 3 and sheet.shape[0] > 300 and sheet.shape[1] > 300
    assert sheet[..., :3].std() > 0.05  # not a blank canvas


def test_write_gallery_with_no_subgoal_and_bad_records(tmp_path):
    html_path, sheet_path = write_gallery([], tmp_path)
    assert "No sub-goal yet" in html_path.read_text() and sheet_path.stat().st_size > 0
    with pytest.raises(ValueError, match="at least 'id' and 'image'"):
        write_gallery([{"id": 0}], tmp_path)
    with pytest.raises(ValueError, match="uint8"):
        write_gallery([{"id": 0, "image": np.zeros((4, 4, 3), np.float32)}], tmp_path)


def test_cli_reports_a_missing_model(tmp_path, capsys):
    missing = str(tmp_path / "no_such_model")
    assert main([missing]) != 0
    assert "no saved model" in capsys.readouterr().err
    result = subprocess.run(
        [sys.executable, "-m", "sb3_hhp.gallery", missing, "--out", str(tmp_path / "g")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode != 0
    assert "no saved model" in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "g").exists()


def test_cli_reports_a_file_that_is_not_a_model(tmp_path, capsys):
    bogus = tmp_path / "model.zip"
    bogus.write_bytes(b"not a zip archive")
    assert main([str(bogus)]) == 1
    assert "cannot load the HhP model" in capsys.readouterr().err


def test_write_gallery_names_each_subgoal_and_explains_its_columns(tmp_path):
    given = records(2)
    given[0]["name"] = "carrying key, facing locked door"
    html_path, _ = write_gallery(given, tmp_path)
    page = html_path.read_text()
    assert "carrying key, facing locked door" in page
    for column in ("found at step", "success", "chosen", "score"):
        assert f"<dt>{column}</dt>" in page
