"""Checkpoints are atomic (a crash mid-write never damages the previous one) and round-trip exactly."""
import os

import numpy as np
import pytest

from d2gs_np.train import checkpoint as ck


def _arrays(rng):
    return {"params/static.means": rng.normal(size=(5, 3)), "adam/step": np.array(7),
            "params/dynamic.deform_means": rng.normal(size=(2, 6, 3)).astype(np.float32)}


def test_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(0)
    arrays = _arrays(rng)
    meta = {"step": 12, "config": {"a": [1, 2]}, "name": "x"}
    ck.save_checkpoint(tmp_path / "c.npz", arrays, meta)
    got, got_meta = ck.load_checkpoint(tmp_path / "c.npz")
    assert got_meta == meta
    assert set(got) == set(arrays)
    for k in arrays:
        assert got[k].dtype == arrays[k].dtype
        np.testing.assert_array_equal(got[k], arrays[k])


def test_failed_write_keeps_previous_checkpoint_and_leaves_no_temp(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    first = _arrays(rng)
    ck.save_checkpoint(tmp_path / "c.npz", first, {"step": 1})

    def crash(src, dst):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(ck.os, "replace", crash)
    with pytest.raises(OSError):
        ck.save_checkpoint(tmp_path / "c.npz", _arrays(rng), {"step": 2})
    monkeypatch.undo()
    got, meta = ck.load_checkpoint(tmp_path / "c.npz")
    assert meta["step"] == 1
    np.testing.assert_array_equal(got["params/static.means"], first["params/static.means"])
    assert sorted(os.listdir(tmp_path)) == ["c.npz"], "temporary file left behind"


def test_missing_and_corrupt_checkpoints_name_the_file(tmp_path):
    for load in (ck.load_checkpoint, ck.load_checkpoint_meta):
        with pytest.raises(FileNotFoundError, match="nope.npz"):
            load(tmp_path / "nope.npz")
        bad = tmp_path / "bad.npz"
        bad.write_bytes(b"not a zip file")
        with pytest.raises(ValueError, match="bad.npz"):
            load(bad)


def test_the_metadata_alone_is_the_full_load_s_metadata(tmp_path):
    meta = {"step": 41, "seconds": 3.5, "left_out": ["blur_model"]}
    ck.save_checkpoint(tmp_path / "c.npz", _arrays(np.random.default_rng(3)), meta)
    assert ck.load_checkpoint_meta(tmp_path / "c.npz") == ck.load_checkpoint(tmp_path / "c.npz")[1] == meta


def test_atomic_write_text_replaces_whole_file(tmp_path):
    p = tmp_path / "m.json"
    ck.atomic_write_text(p, "a" * 1000)
    ck.atomic_write_text(p, "b")
    assert p.read_text() == "b"
