import numpy as np
import pytest

from sb3_hhp.preferences.codecs import decode_png
from sb3_hhp.preferences.store import PreferenceStore
from sb3_hhp.subgoal_table import SubgoalTable


def test_subgoals_are_replaced_as_a_whole():
    table = SubgoalTable(PreferenceStore())
    image = np.random.default_rng(0).integers(0, 255, (8, 8, 3), dtype=np.uint8)
    table.put(
        [
            {"id": 1, "image": image, "found_at": 500, "success_rate": 0.25, "chosen_recently": 3, "mean_score": 0.7},
            {"id": 0, "image": image[:4], "found_at": 0, "success_rate": None, "chosen_recently": 0, "mean_score": None},
        ]
    )
    records = table.records()
    assert [r["id"] for r in records] == [0, 1]
    assert records[1]["found_at"] == 500 and records[1]["success_rate"] == 0.25 and records[1]["mean_score"] == 0.7
    assert records[0]["success_rate"] is None
    np.testing.assert_array_equal(records[1]["image"], image)
    np.testing.assert_array_equal(decode_png(table.png(0)), image[:4])
    table.put([{"id": 5, "image": image}])
    assert [r["id"] for r in table.records(with_images=False)] == [5]
    with pytest.raises(ValueError, match="appears twice"):
        table.put([{"id": 2, "image": image}, {"id": 2, "image": image}])
    assert [r["id"] for r in table.records(with_images=False)] == [5]  # unchanged after the error
    with pytest.raises(KeyError):
        table.png(1)


def test_names_bad_ids_and_a_table_shared_through_the_file(tmp_path):
    store = PreferenceStore(tmp_path / "prefs.db")
    table = SubgoalTable(store)
    image = np.zeros((4, 4, 3), np.uint8)
    table.put([{"id": 3, "image": image, "name": "carrying key, facing locked door"}, {"id": 4, "image": image}])
    assert [r["name"] for r in table.records(with_images=False)] == ["carrying key, facing locked door", None]
    with pytest.raises(KeyError, match="ids are in"):
        table.png(10**22)
    with pytest.raises(ValueError, match="Sub-goal id must be in"):
        table.put([{"id": -1, "image": image}])
    with pytest.raises(ValueError, match="needs at least 'id' and 'image'"):
        table.put([{"id": 1}])
    with pytest.raises(ValueError, match="needs a PreferenceStore"):
        SubgoalTable(str(tmp_path / "prefs.db"))
    # another process's view of the same file (the labeling server) reads what the trainer wrote
    with PreferenceStore(tmp_path / "prefs.db", create=False) as other:
        assert [r["id"] for r in SubgoalTable(other).records(with_images=False)] == [3, 4]
    store.close()
