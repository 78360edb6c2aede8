"""Every gscan-ros subcommand refuses a bad number or path the same way: exit status 1, one
line on stderr naming the argument, no traceback, nothing written. The CLI runs in-process
from a scratch working directory, so a default output folder (runs/, out/) written by
mistake would show up in the snapshot."""
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gscan_ros.cli import SUBCOMMANDS, main
from gscan_ros.errors import CheckpointError
from gscan_ros.model.checkpoint import read_checkpoint, save_checkpoint
from gscan_ros.model.policy import Policy, default_checkpoint_path
from gscan_ros.runtime import available_cpus

from model_support import tiny_checkpoint

CPUS = available_cpus()

# (argv, text the error line must contain). {data}: an existing dataset path, {file}: an
# existing plain file, {missing}: a path that does not exist, {long}: a name longer than any
# file system takes, {ckpt}: a valid checkpoint.
BAD_ARGUMENTS = [
    # generate
    ("generate --out {tmp}/g --examples 5 --seed -1", "--seed"),
    ("generate --out {tmp}/g --examples 5 --seed x", "--seed"),
    ("generate --out {tmp}/g --examples 0", "--examples"),
    ("generate --out {tmp}/g --examples -3", "--examples"),
    ("generate --out {tmp}/g --examples 5 --workers 0", "--workers"),
    (f"generate --out {{tmp}}/g --examples 5 --workers {CPUS + 1}", f"only {CPUS} CPU(s)"),
    ("generate --out {tmp}/g --examples 5 --num-resampling 0", "--num-resampling"),
    ("generate --out {tmp}/g --examples 5 --percentage-train 0", "--percentage-train"),
    ("generate --out {tmp}/g --examples 5 --percentage-train 1.5", "--percentage-train"),
    ("generate --out {tmp}/g --examples 5 --percentage-train nan", "--percentage-train"),
    ("generate --out {tmp}/g --examples 5 --percentage-dev 1", "--percentage-dev"),
    ("generate --out {tmp}/g --examples 5 --percentage-dev -0.1", "--percentage-dev"),
    ("generate --out {tmp}/g --examples 5 --k-shot -3", "--k-shot"),
    ("generate --out {tmp}/g --examples 5 --cut-off-target-length 0", "--cut-off-target-length"),
    ("generate --out {file} --examples 5", "--out"),
    ("generate --out {file}/sub --examples 5", "--out"),
    # augment
    ("augment --data {missing} --out {tmp}/a --method geca", "--data"),
    ("augment --data {data} --out {file} --method geca", "--out"),
    ("augment --data {data} --out {tmp}/a --method eda", "--method"),
    ("augment --data {data} --out {tmp}/a --method geca --examples 0", "--examples"),
    ("augment --data {data} --out {tmp}/a --method geca --seed -1", "--seed"),
    # verify
    ("verify {missing}", "DATASET"),
    ("verify {long}", "File name too long"),
    ("evaluate --data {data} --out {long}", "--out"),
    ("evaluate --data {data} --attention --no-predictions", "--no-predictions"),
    ("render {data} --out {long}.gif", "--out"),
    ("bag repair {missing} --out {tmp}/r", "BAG"),
    ("bag repair {data} --out {file}", "--out"),
    ("verify {data} --limit 0", "--limit"),
    ("verify {data} --splits=", "--splits"),
    ("verify {data} --splits=train,,dev", "--splits"),
    ("verify {data} --limit x", "--limit"),
    ("verify {data} --show -1", "--show"),
    ("verify {data} --allow-partial", "--allow-partial"),  # for bags only: not ignored
    ("verify {data} --include-incomplete", "--include-incomplete"),
    # render
    ("render {missing} --out {tmp}/a.png", "DATASET"),
    ("render {data} --out {tmp}/a.gif --fps 0", "--fps"),
    ("render {data} --out {tmp}/a.gif --fps -2", "--fps"),
    ("render {data} --out {tmp}/a.gif --fps nan", "--fps"),
    ("render {data} --out {tmp}/a.gif --fps 1000", "--fps"),
    ("render {data} --out {tmp}/a.gif --fps 0.001", "--fps"),  # a GIF frame lasts at most 655.35 s
    ("render {data} --out {tmp}/a.png --fps 7", "--fps"),  # a PNG has no frame rate: not ignored
    ("render {data} --out {tmp}/a.png --cell-px -5", "--cell-px"),
    ("render {data} --out {tmp}/a.png --cell-px 0", "--cell-px"),
    ("render {data} --out {tmp}/a.png --cell-px 100000", "--cell-px"),
    ("render {data} --out {tmp}/a.png --index -1", "--index"),
    ("render {data} --out {missing}/a.png", "--out"),
    ("render {data} --out {tmp}/a.txt", "--out"),
    ("render {data} --out {tmp}", "--out"),
    ("render {data} --out {tmp}/folder.png", "--out"),
    ("render {data} --out {png}", "--overwrite"),
    # parse (no numbers or paths: its choices fail the same way)
    ("parse walk to a circle --lexicon x", "--lexicon"),
    ("parse walk to a circle --all --parser dependency", "--all"),
    # train
    ("train --data {missing}", "--data"),
    ("train --data {data} --config {missing}", "--config"),
    ("train --data {data} --out {file}", "--out"),
    ("train --data {data} --set lr=nan", "lr"),
    ("train --data {data} --set lr=[", "lr"),
    ("train --data {data} --set model.rnn_dim=-5", "rnn_dim"),
    ("train --data {data} --set model.rnn_dim=[1,2]", "rnn_dim"),
    ("train --data {data} --set model.cnn_kernels=5", "cnn_kernels"),
    ("train --data {data} --set model.rnn_dim=100000", "rnn_dim must be at most 512"),
    ("train --data {data} --set model.rnn_layers=1000", "rnn_layers must be at most 8"),
    ("train --data {data} --set model.cnn_kernels=[100001]", "odd integers in [1, 31]"),
    (f"train --data {{data}} --set threads={CPUS + 1}", f"only {CPUS} CPU(s)"),
    ("train --data {data} --config {yaml_list}", "batch_size"),
    ("train --data {data} --config {yaml_model_list}", "model"),
    ("train --data {data} --config {yaml_latin1}", "UTF-8"),
    ("train --data {data} --device tpu", "--device"),
    ("train --data {data} --include-incomplete", "include_incomplete"),  # every dataset.txt example is complete
    # evaluate
    ("evaluate --data {missing}", "--data"),
    ("evaluate --data {data} --checkpoint {missing}", "--checkpoint"),
    ("evaluate --data {data} --max-examples -3", "--max-examples"),
    ("evaluate --data {data} --batch-size 0", "--batch-size"),
    ("evaluate --data {data} --threads -4", "--threads"),
    (f"evaluate --data {{data}} --threads {CPUS + 1}", f"only {CPUS} CPU(s)"),
    ("evaluate --data {data} --seed -1", "--seed"),
    ("evaluate --data {data} --seed 7", "--max-examples"),  # no subset to seed: not ignored
    ("evaluate --data {data} --out {file}", "--out"),
    ("evaluate --data {data} --device tpu", "--device"),
    # experiment
    ("experiment {missing}", "PLAN"),
    ("experiment {file}", "mapping"),
    ("experiment {yaml_list} --dry-run", "batch_size"),
    ("experiment {file} --parallel 0", "--parallel"),
    (f"experiment {{file}} --parallel {CPUS + 1}", "--parallel"),
    ("experiment {file} --threads 0", "--threads"),
    ("experiment {file} --worker 2/2", "--worker"),
    ("experiment {file} --worker x", "--worker"),
    ("experiment {file} --results {file}", "--results"),
    # report
    ("report {missing} --out {tmp}/t.md", "RUN_DIR"),
    ("report {tmp} --out {tmp}/t.txt", "--out"),
    ("report {tmp} --out {missing}/t.md", "--out"),
    ("report {tmp} --out {png}", "--out"),
    ("report {tmp} --out {tmp}/t.md", "results.json"),
    # explain
    ("explain --out {tmp}/a.txt", "--out"),
    ("explain --data {missing} --out {tmp}/a.png", "--data"),
    ("explain --checkpoint {missing} --out {tmp}/a.png", "--checkpoint"),
    ("explain --step -1 --out {tmp}/a.png", "--step"),
    ("explain --max-columns 1 --out {tmp}/a.png", "--max-columns"),
    ("explain --metrics --data {data} --max-examples -1", "--max-examples"),
    ("explain --out {png}", "--overwrite"),
    ("explain --progression {file} --out {tmp}/a.png", "--progression"),
    ("explain --progression {missing} --out {tmp}/a.png", "--progression"),
    ("explain --metrics --data {data} --progression {file}", "--progression"),
    ("explain --out {tmp}/a.png --device gpu", "--device"),
    # options the mode would not use: refused, not ignored
    ("explain --metrics --data {data} --step 3", "--step"),
    ("explain --metrics --data {data} --index 3", "--index"),
    ("explain --out {tmp}/a.png --max-examples 5", "--max-examples"),
    ("explain --out {tmp}/a.png --fps 9", "--fps"),
    ("explain --out {tmp}/a.png --seed 3 --split visual", "--split"),
    ("explain --out {tmp}/a.png --max-columns 4", "--max-columns"),
    ("explain --out /proc/a.png", "while writing /proc/a.png: No such file or directory (/proc/.a.png.lock)"),
    (f"explain --out {{tmp}}/a.png --threads {CPUS + 1}", f"only {CPUS} CPU(s)"),
    # replay
    ("replay {missing}", "does not exist"),
    ("replay {data} --max-episodes 0", "--max-episodes"),
    ("replay {data} --batch-size 0", "--batch-size"),
    ("replay {data} --checkpoint {missing}", "--checkpoint"),
    # demo
    ("demo --episodes 0", "--episodes"),
    ("demo --command=", "--command"),
    ("demo --timeout 0", "--timeout"),
    ("demo --timeout nan", "--timeout"),
    ("demo --max-steps 0", "--max-steps"),
    ("demo --index -1", "--index"),
    ("demo --seed -1", "--seed"),
    # bringup
    ("bringup --max-steps -5", "--max-steps"),
    ("bringup --index -1", "--index"),
    ("bringup --seed -2", "--seed"),
    ("bringup --record {file}/bag", "--record"),
    ("bringup --checkpoint {missing}", "--checkpoint"),
    ("bringup --overwrite", "--record"),  # nothing to overwrite: not ignored
    ("bringup --dataset {data} --seed 5", "--seed"),  # the dataset's examples, not sampled worlds
    ("bringup --split dev", "--split"),  # sampled worlds have no split
    ("demo --dataset {data} --grid-size 8", "--grid-size"),
    ("demo --out {file}/run", "--out"),
    ("demo --parser constituency", "reads semantic parses"),
    ("train --data {data} --config {yaml_empty}", "holds no settings"),
    ("evaluate --data {data} --checkpoint {cut}", "is truncated"),
    ("bringup --record {tmp}", "exists and is not empty (pass --overwrite to replace a bag there)"),
    ("train --data {data} --config {yaml_twice}", "key 'batch_size' appears twice"),
    ("explain --metrics --data {data} --overwrite", "--overwrite"),  # the policy would reject every graph
    ("demo --parser nosuch", "--parser 'nosuch'"),
    ("demo --checkpoint {file}", "is not a checkpoint"),
    ("bringup --grid-size 12", "reads 6x6 worlds"),
    ("verify {mcap}", "a storage file of a bag; pass the bag's folder"),
    ("train --data {mcap}", "a storage file of a bag; pass the bag's folder"),
]
if not torch.cuda.is_available():  # CI: a GPU asked for and not there
    BAD_ARGUMENTS += [(f"{command} --device cuda", "no CUDA GPU") for command in
                      ("train --data {data}", "evaluate --data {data}", "explain --out {tmp}/a.png")]


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """A scratch cwd with the inputs the table refers to."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "dataset.txt").write_text("{}")
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "old.png").write_bytes(b"png")
    (tmp_path / "folder.png").mkdir()
    (tmp_path / "list.yaml").write_text("batch_size: [1, 2]\n")
    (tmp_path / "model_list.yaml").write_text("model: [1, 2]\n")
    (tmp_path / "latin1.yaml").write_bytes("lr: 0.001 # r\xe9glage\n".encode("latin-1"))
    (tmp_path / "empty.yaml").write_text("# nothing yet\n")
    (tmp_path / "cut.pt").write_bytes(default_checkpoint_path().read_bytes()[:4096])  # a copy that did not finish
    (tmp_path / "twice.yaml").write_text("batch_size: 50\nlr: 0.001\nbatch_size: 200\n")
    (tmp_path / "bag_0.mcap").write_bytes(b"\x89MCAP0\r\n")  # one file of a bag, not its folder
    return tmp_path


def _fill(template: str, tmp) -> list[str]:
    values = {"tmp": tmp, "data": tmp / "dataset.txt", "file": tmp / "notes.txt", "missing": tmp / "missing",
              "png": tmp / "old.png", "yaml_list": tmp / "list.yaml", "yaml_model_list": tmp / "model_list.yaml",
              "yaml_latin1": tmp / "latin1.yaml",
              "yaml_empty": tmp / "empty.yaml", "yaml_twice": tmp / "twice.yaml", "cut": tmp / "cut.pt",
              "mcap": tmp / "bag_0.mcap",
              "long": tmp / ("n" * 300)}
    return [word.format(**values) for word in template.split()]


def _snapshot(root) -> dict:
    return {p.relative_to(root): p.read_bytes() if p.is_file() else None for p in sorted(root.rglob("*"))}


def run_cli(argv: list[str]) -> int:
    """main()'s exit status, whether it returns it or the parser exits."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


def assert_refused(capsys, argv: list[str], names: str) -> str:
    code = run_cli(argv)
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 1, (argv, captured.err)
    assert len(lines) == 1, captured.err
    assert names in lines[0] and "Traceback" not in captured.err
    command = " ".join(argv[:2]) if argv[0] == "bag" else argv[0]
    assert lines[0].startswith(f"gscan-ros {command}: error:")
    return lines[0]


def test_the_table_covers_every_subcommand():
    assert {row[0].split()[0] for row in BAD_ARGUMENTS} == set(SUBCOMMANDS)


@pytest.mark.parametrize("template, names", BAD_ARGUMENTS, ids=[row[0] for row in BAD_ARGUMENTS])
def test_bad_argument_is_one_line_exit_1_and_writes_nothing(workdir, capsys, template, names):
    before = _snapshot(workdir)
    assert_refused(capsys, _fill(template, workdir), names)
    assert _snapshot(workdir) == before


EMPTY_PATHS = [
    ["generate", "--out", ""], ["train", "--data", "dataset.txt", "--out", ""], ["evaluate", "--checkpoint", ""],
    ["verify", ""], ["replay", ""], ["render", ""], ["report", "", "--out", "r.md"],
    ["bag", "repair", "", "--out", "r"],
    ["experiment", "plan.yaml", "--data-root", "", "--dry-run"], ["demo", "--out", ""],
]


@pytest.mark.parametrize("argv", EMPTY_PATHS, ids=[" ".join(a[:2]) for a in EMPTY_PATHS])
def test_an_empty_path_is_refused_not_read_as_the_current_folder(workdir, capsys, argv):
    """An unset shell variable (`--out "$OUT"`) must not write into, or read, the current folder."""
    (workdir / "plan.yaml").write_text("runs: []\n")
    before = _snapshot(workdir)
    assert_refused(capsys, argv, "empty path")
    assert _snapshot(workdir) == before


@pytest.mark.parametrize("command", SUBCOMMANDS)
def test_help_still_works(command, capsys):
    assert run_cli([command, "--help"]) == 0
    assert capsys.readouterr().out.startswith(f"usage: gscan-ros {command}")


def test_render_overwrite_replaces_an_existing_file(workdir):
    from gscan_ros.data.generate import GenerationConfig, generate_dataset

    generate_dataset(workdir / "data", GenerationConfig(seed=3, max_examples=30))
    assert main(["render", str(workdir / "data"), "--out", str(workdir / "old.png"), "--cell-px", "8",
                 "--overwrite"]) == 0
    assert (workdir / "old.png").read_bytes().startswith(b"\x89PNG")


# ----------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def checkpoint_dir(tmp_path_factory):
    return tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt").parent


def _broken(checkpoint_dir, name: str, edit) -> str:
    ckpt = read_checkpoint(checkpoint_dir / "tiny.pt")
    edit(ckpt)
    path = checkpoint_dir / f"{name}.pt"
    save_checkpoint(path, ckpt)
    return str(path)


def _nan_weight(ckpt):
    name = sorted(ckpt["state_dict"])[0]
    ckpt["state_dict"][name] = ckpt["state_dict"][name].clone().fill_(float("nan"))


BROKEN = {
    "nan_weights": (_nan_weight, "NaN"),
    "inf_weights": (lambda c: c["state_dict"].update(
        {k: torch.full_like(v, float("inf")) for k, v in list(c["state_dict"].items())[-1:]}), "infinite"),
    "empty_vocabulary": (lambda c: c["vocabulary"].update(modules=[]), "empty vocabulary"),
    "negative_dimension": (lambda c: c["model_config"].update(rnn_dim=-5), "rnn_dim"),
    "list_dimension": (lambda c: c["model_config"].update(att_dim=[4]), "att_dim"),
    "zero_heads": (lambda c: c["vocabulary"]["modules"][0].update(num_heads=0), "heads"),
}


@pytest.mark.parametrize("name", BROKEN)
def test_unusable_checkpoint_is_refused_at_load(checkpoint_dir, name):
    edit, message = BROKEN[name]
    path = _broken(checkpoint_dir, name, edit)
    with pytest.raises(CheckpointError, match=message):
        Policy.from_checkpoint(path)


def test_evaluate_refuses_nan_weights_naming_the_tensor(checkpoint_dir, workdir, capsys):
    path = _broken(checkpoint_dir, "nan_weights", _nan_weight)
    tensor = sorted(torch.load(path, weights_only=True)["state_dict"])[0]
    before = _snapshot(workdir)
    line = assert_refused(capsys, ["evaluate", "--checkpoint", path, "--data", str(workdir / "dataset.txt")], tensor)
    assert "NaN" in line
    assert _snapshot(workdir) == before


def test_policy_node_refuses_a_bad_checkpoint_at_start(checkpoint_dir, capsys, monkeypatch):
    from gscan_ros.nodes import policy_node

    from ros_helpers import fresh_domain_id

    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    path = _broken(checkpoint_dir, "empty_vocabulary", BROKEN["empty_vocabulary"][0])
    assert policy_node.main(["--ros-args", "-p", f"checkpoint:={path}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "empty vocabulary" in err[0]


@pytest.mark.parametrize("buffered", [True, False], ids=["left to the flush at exit", "unbuffered: at the print"])
def test_a_standard_output_that_takes_no_more_is_one_line(buffered, monkeypatch):
    """`> /dev/full`: the error of a print, or of the interpreter's flush at exit, is one line."""
    monkeypatch.delenv("PYTHONUNBUFFERED", raising=False)
    if not buffered:
        monkeypatch.setenv("PYTHONUNBUFFERED", "1")
    with open("/dev/full", "w") as full:
        done = subprocess.run([sys.executable, "-m", "gscan_ros.cli", "parse", "walk to a red circle"], stdout=full,
                              stderr=subprocess.PIPE, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 1
    assert done.stderr.splitlines() == [
        "gscan-ros parse: error: cannot write to standard output: No space left on device"]
