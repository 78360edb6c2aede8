"""No writer deletes or replaces a user's files without an explicit flag."""
import pytest

from gscan_ros.cli import main
from gscan_ros.data.bag import BagWriter
from gscan_ros.errors import DatasetFormatError

from model_support import tiny_checkpoint


def _user_folder(path):
    """A folder that holds a metadata.yaml among the user's own files."""
    path.mkdir()
    (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (path / "thesis.tex").write_text("years of work")
    (path / "figures").mkdir()
    (path / "figures" / "plot.png").write_bytes(b"png")
    return path


def _snapshot(path):
    return {p.relative_to(path): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def test_bringup_record_refuses_a_folder_that_holds_a_metadata_yaml(tmp_path, monkeypatch, capsys):
    from ros_helpers import fresh_domain_id  # the one test here that starts nodes (in-process)

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    folder = _user_folder(tmp_path / "work")
    before = _snapshot(folder)
    code = main(["bringup", "--checkpoint", str(tiny_checkpoint(tmp_path / "tiny.pt")), "--record", str(folder)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and str(folder) in err[0] and "Traceback" not in err[0]
    assert _snapshot(folder) == before


def _repair_into(folder, overwrite):
    """`bag repair` of a small bag into `folder`."""
    from gscan_ros.data.bag import repair_bag, write_bag

    from bag_support import make_episodes

    write_bag(folder.parent / "source", make_episodes(2))
    repair_bag(folder.parent / "source", folder, overwrite=overwrite)


BAG_WRITERS = {"BagWriter": lambda folder, overwrite: BagWriter(folder, overwrite=overwrite).open(),
               "bag repair": _repair_into}


@pytest.mark.parametrize("writer", BAG_WRITERS)
@pytest.mark.parametrize("overwrite", [False, True])
def test_bag_writers_never_delete_foreign_files(tmp_path, overwrite, writer):
    """One rule for every bag writer (`bag_metadata.replaceable_bag`): a metadata.yaml among
    a user's files does not make the folder a bag to replace."""
    folder = _user_folder(tmp_path / "work")
    before = _snapshot(folder)
    with pytest.raises(DatasetFormatError, match="refusing to overwrite|pass --overwrite"):
        BAG_WRITERS[writer](folder, overwrite)
    assert _snapshot(folder) == before


def test_bag_writer_overwrite_replaces_only_an_old_bag(tmp_path):
    with BagWriter(tmp_path / "bag"):
        pass
    with pytest.raises(DatasetFormatError, match="pass --overwrite"):
        BagWriter(tmp_path / "bag").open()
    with BagWriter(tmp_path / "bag", overwrite=True):
        pass
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == ["bag_0.mcap", "metadata.yaml"]


def test_demo_overwrite_leaves_no_gif_of_an_earlier_longer_demo(tmp_path):
    from gscan_ros.cli.demo import _earlier_gifs

    for name in ("episode_1.gif", "episode_2.gif", "episode_10.gif", "episode_x.gif", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in _earlier_gifs(tmp_path, 2)] == ["episode_10.gif"]  # not a file it did not write


def test_demo_refuses_a_non_empty_out_without_overwrite(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep")
    code = main(["demo", "--out", str(out)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1 and "--overwrite" in err[0]
    assert (out / "notes.txt").read_text() == "keep" and len(list(out.iterdir())) == 1
