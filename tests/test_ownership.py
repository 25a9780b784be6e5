"""recon.runner.ownership and the batch's capture folders: who may write where, and which files recon may replace."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from recon.app.batch import Capture, place_captures
from recon.errors import InputError
from recon.runner.ownership import claim_folder, marker_name
from recon.stages import scene_parts


def _build(owned, files: dict[str, str]) -> None:
    with owned.staging() as staged:
        for name, text in files.items():
            (staged / name).parent.mkdir(parents=True, exist_ok=True)
            (staged / name).write_text(text)
        owned.replace_with(staged)


def test_a_record_lists_what_recon_wrote_and_only_that_is_replaced(tmp_path: Path) -> None:
    out = tmp_path / "out"
    _build(claim_folder(out, "render", scene_parts), {"a.png": "1", "sub/b.png": "2"})
    assert json.loads((out / marker_name("render")).read_text())["files"] == ["a.png", "sub/b.png"]
    (out / "sub" / "mine.txt").write_text("user")
    _build(claim_folder(out, "render", scene_parts), {"c.png": "3"})
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()) == [
        ".recon-render.json", "c.png", "sub/mine.txt"]  # sub/ stays: it holds the user's file
    with pytest.raises(InputError, match="holds a recon render, not a recon export"):
        claim_folder(out, "export", scene_parts)


def test_a_failed_build_into_a_new_folder_leaves_nothing(tmp_path: Path) -> None:
    out = tmp_path / "new"
    with pytest.raises(RuntimeError), claim_folder(out, "export", scene_parts).staging():
        raise RuntimeError("the export failed")
    assert not out.exists()


def test_an_export_record_from_before_file_lists_owns_the_whole_folder(tmp_path: Path) -> None:
    """Earlier exports recorded no file list; they replaced the whole folder, so all its files were recon's."""
    out = tmp_path / "export"
    (out / "images").mkdir(parents=True)
    (out / "images" / "a.jpg").write_text("x")
    (out / "transforms.json").write_text("{}")
    (out / marker_name("export")).write_text(json.dumps({"format": "nerfstudio", "frame": "normalized"}))
    owned = claim_folder(out, "export", scene_parts)
    assert owned.files == {"images/a.jpg", "transforms.json"} and owned.record["format"] == "nerfstudio"


def test_a_link_inside_the_folder_is_never_written_through(tmp_path: Path) -> None:
    out, elsewhere = tmp_path / "out", tmp_path / "photos"
    elsewhere.mkdir()
    _build(claim_folder(out, "export", scene_parts), {"points.ply": "1"})
    (out / "images").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(InputError, match="images"):
        _build(claim_folder(out, "export", scene_parts), {"images/a.jpg": "2"})
    assert list(elsewhere.iterdir()) == [] and (out / "points.ply").is_file()


def test_batch_captures_keep_their_folders_and_a_taken_name_gets_the_next(tmp_path: Path) -> None:
    out = tmp_path / "out"
    a, b, c = (tmp_path / p / "shoe" for p in ("a", "b", "c"))
    owned = claim_folder(out, "batch", scene_parts)
    assert place_captures([Capture("shoe", a)], owned) == [] and owned.record["captures"] == {"shoe": str(a)}
    owned.save(["batch.md"])
    (out / "shoe-2").mkdir()  # the user's own folder
    owned = claim_folder(out, "batch", scene_parts)
    captures = [Capture("shoe", b), Capture("shoe-2", a), Capture("shoe-3", c)]
    notes = place_captures(captures, owned)
    assert [x.name for x in captures] == ["shoe-3", "shoe", "shoe-4"]  # a keeps its folder; shoe-2 is not recon's
    assert notes[0] == f"{b} → {out / 'shoe-3'}: {out / 'shoe'} holds {a}"
    assert owned.record["captures"] == {"shoe": str(a), "shoe-3": str(b), "shoe-4": str(c)}


def test_a_batch_folder_from_before_records_is_taken_only_when_it_holds_nothing_else(tmp_path: Path) -> None:
    from recon.app.batch import adopt_unrecorded_batch

    out = tmp_path / "batch"
    (out / "shoe").mkdir(parents=True)
    (out / "shoe" / "manifest.json").write_text("{}")
    (out / "batch.md").write_text("# recon batch")
    (out / "batch.json").write_text(json.dumps({"captures": [{"name": "shoe", "source": "/x/shoe", "folder": str(out / "shoe")}]}))
    (out / "notes.txt").write_text("mine")
    adopt_unrecorded_batch(out)
    with pytest.raises(InputError, match="notes.txt"):
        claim_folder(out, "batch", scene_parts)
    (out / "notes.txt").unlink()
    adopt_unrecorded_batch(out)
    owned = claim_folder(out, "batch", scene_parts)
    assert owned.record["captures"] == {"shoe": "/x/shoe"} and owned.files == {"batch.md", "batch.json"}
