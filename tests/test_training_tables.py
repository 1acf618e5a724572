"""bench/training_tables.py: docs/training.md's marked tables are rewritten from the benches' JSON, nothing else."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _tables():
    spec = importlib.util.spec_from_file_location("training_tables", ROOT / "bench" / "training_tables.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _video(mode="quick"):
    rows = [{"model": m, "steps": s, "sampler": "flow", "value": v, "psnr": 15.0, "mode_error": 0.4, "seed": seed,
             "split": "test"} for seed in (0, 1) for m, s, v in (("fm-only", 1, 0.44), ("fm-only", 20, 0.21),
                                                                  ("shortcut", 1, 0.30 + 0.02 * seed))]
    return {"metric": "swd", "higher_is_better": False, "mode": mode, "split": "test", "rows": rows,
            "train_scenes": [1, 2], "test_scenes": [3], "clips": 8, "wall_s": 1.0, "cpu_s": 1.0,
            "targets": {"shortcut_beats_fm_at_1": True}}


def _recon(test_scenes=(5, 6)):
    rows = [{"model": m, "refine_iters": r, "split": sp, "ate": ate, "rpe_t": 0.1, "rpe_r": 2.0, "abs_rel": 0.1,
             "novel_psnr": None} for sp in ("test", "val") for r in (0, 20)
            for m, ate in (("trained", 0.1), ("init", 0.36))]
    return {"mode": "quick", "rows": rows, "train_scenes": [1, 2], "val_scenes": [3], "test_scenes": list(test_scenes),
            "split_seeds": {"train": 7, "val": 8, "test": 2026}, "steps": {"stage1": 10, "stage2": 0},
            "wall_s": 1.0, "cpu_s": 1.0}


def test_marked_sections_are_rewritten_from_json_and_the_rest_is_kept(tmp_path):
    tables = _tables()
    doc = tmp_path / "training.md"
    doc.write_text("intro\n<!-- BEGIN video-quick -->\nold\n<!-- END video-quick -->\nmiddle\n"
                   "<!-- BEGIN recon-quick -->\nold\n<!-- END recon-quick -->\nend\n")
    (tmp_path / "v.json").write_text(json.dumps(_video()))
    (tmp_path / "r.json").write_text(json.dumps(_recon()))
    args = ["--video", str(tmp_path / "v.json"), "--recon", str(tmp_path / "r.json"), "--doc", str(doc)]
    assert tables.main([*args, "--check"]) == 1  # stale
    assert tables.main(args) == 0
    text = doc.read_text()
    assert text.startswith("intro\n") and "\nmiddle\n" in text and text.endswith("end\n") and "old" not in text
    assert "| shortcut | 1 | flow | 0.3100 ± 0.0100 |" in text  # mean ± std over the two seeds
    assert "| test | trained | 0 (paper) | 0.1000 |" in text and "20 (not in the paper)" in text
    assert "test: init / trained ATE = 3.60x (meets the 3x target)" in text
    assert "disjoint from train and val: yes" in text
    assert tables.main([*args, "--check"]) == 0  # up to date


def test_overlapping_test_scenes_are_flagged_and_missing_markers_name_the_fix(tmp_path):
    tables = _tables()
    assert "disjoint from train and val: **no**" in tables.recon_table(_recon(test_scenes=(2, 9)))
    doc = tmp_path / "training.md"
    doc.write_text("no markers\n")
    (tmp_path / "v.json").write_text(json.dumps(_video(mode="full")))
    with pytest.raises(SystemExit, match="BEGIN video-full"):
        tables.main(["--video", str(tmp_path / "v.json"), "--doc", str(doc)])


def test_docs_training_tables_are_the_committed_results():
    """docs/training.md's quick tables are what training_tables.py writes from docs/results/training/*.json."""
    res = ROOT / "docs" / "results" / "training"
    args = [f"--video={p}" for p in sorted(res.glob("video_quick_*.json"))]
    args += [f"--recon={p}" for p in sorted(res.glob("recon_quick*.json"))]
    assert args, f"no results under {res}"
    assert _tables().main([*args, "--check"]) == 0, "stale: run bench/training_tables.py with the JSON under " + str(res)
