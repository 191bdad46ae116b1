"""CLI conventions (minority/cliargs.py), over every subcommand: `--help` prints that
subcommand's own usage with every default shown once; an unknown flag or a missing input
prints an error and exits 2, leaving nothing behind; `-o/--out` is the one spelling of what a
command writes, and its directory is created; `minority --version`; the top-level help names
every command and every oracle step; `oracle spec` is for the run id the sim will use."""

import argparse
import shutil

import h5py
import pytest

from minority.cli import build_parser, main, score_parser, version
from minority.oracle_cli import STEPS


def subcommands(parser: argparse.ArgumentParser, path=()) -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every command path of the parser tree, e.g. ("oracle", "train"), ("log", "repair")."""
    out = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out[(*path, name)] = sub
                out.update(subcommands(sub, (*path, name)))
    return out


PARSERS = {**subcommands(build_parser()), ("report", "score"): score_parser()}
LEAVES = [c for c, p in PARSERS.items() if not any(isinstance(a, argparse._SubParsersAction)
                                                   for a in p._actions)]
COMMANDS = list(PARSERS)
# what each command writes with -o/--out (None: it writes no file of its own, only stdout)
OUTPUT = {("serve",): "DIR", ("sim",): "FILE.h5", ("replay",): "DIR", ("report",): "DIR",
          ("report", "score"): "DIR", ("record",): "FILE.mcap", ("log", "check"): None,
          ("log", "repair"): "OUT.mcap", ("log", "export"): "OUT.mcap",
          ("deploy", "acl"): "FILE", ("demo",): "DIR",
          ("oracle", "dataset"): "DIR", ("oracle", "train"): "OUT.pt",
          ("oracle", "evaluate"): "FILE.json", ("oracle", "diagnose"): None,
          ("oracle", "ship"): "OUT.pt", ("oracle", "rollout"): "DIR",
          ("oracle", "spec"): "FILE.json", ("oracle", "preview"): "FILE.png",
          ("oracle", "export-npz"): "DIR", ("oracle", "follow"): None}
MISSING = "no/such/input"
# each command with input that is not there, or a bad value (exit status 2, nothing written)
BAD_INPUT = {("serve",): ["--spec", MISSING], ("sim",): ["no_such_scene"],
             ("replay",): [MISSING], ("report",): [MISSING],
             ("report", "score"): [MISSING, MISSING], ("record",): ["--compression", "gzip"],
             ("log", "check"): [MISSING], ("log", "repair"): [MISSING],
             ("log", "export"): ["--foxglove", MISSING],
             ("deploy", "acl"): ["--run", "a/b"], ("demo",): ["--frames", "1"],
             ("oracle", "dataset"): ["--config", MISSING], ("oracle", "train"): [MISSING],
             ("oracle", "evaluate"): [MISSING, MISSING],
             ("oracle", "diagnose"): [MISSING, MISSING], ("oracle", "ship"): [MISSING],
             ("oracle", "rollout"): [MISSING, "tiny"], ("oracle", "spec"): [MISSING],
             ("oracle", "preview"): [MISSING, MISSING], ("oracle", "export-npz"): [MISSING],
             ("oracle", "follow"): ["r", "--scene", "no_such_scene"]}


def test_the_tables_name_every_command():
    assert sorted(OUTPUT) == sorted(BAD_INPUT) == sorted(LEAVES)


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_help_is_the_subcommands_own(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: minority {' '.join(command)}")


def said_default(action: argparse.Action) -> bool:
    """Whether the option has a default worth saying (not None, False or empty)."""
    return (bool(action.option_strings) and action.default is not argparse.SUPPRESS
            and action.default not in (None, False, []))


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_help_shows_every_default_once(command, capsys):
    with pytest.raises(SystemExit):
        main([*command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    formatter = PARSERS[command]._get_formatter()
    for action in PARSERS[command]._actions:
        if action.help in (None, argparse.SUPPRESS):
            continue
        expanded = formatter._expand_help(action)
        assert expanded.count("default") <= 1, expanded  # said once
        if said_default(action):
            assert f"(default: {action.default})" in text, action.option_strings


@pytest.mark.parametrize("command", LEAVES, ids=" ".join)
def test_out_is_the_one_output_flag(command):
    flags = {s for a in PARSERS[command]._actions for s in a.option_strings}
    assert "--output" not in flags
    if OUTPUT[command] is None:
        assert "--out" not in flags
    else:
        out = next(a for a in PARSERS[command]._actions if "--out" in a.option_strings)
        assert out.option_strings == ["-o", "--out"] and out.metavar == OUTPUT[command]


@pytest.mark.parametrize("command", COMMANDS, ids=" ".join)
def test_an_unknown_flag_prints_the_subcommands_usage_and_exits_2(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--no-such-flag"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: minority {' '.join(command)}" in err
    # argparse names a missing required argument before an unknown flag
    assert "--no-such-flag" in err or "arguments are required" in err


@pytest.mark.parametrize("command", LEAVES, ids=" ".join)
def test_bad_input_exits_2_and_writes_nothing(command, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    argv = [*command, *BAD_INPUT[command]]
    if OUTPUT[command]:
        argv += ["-o", str(tmp_path / "out" / "x")]
    try:
        status = main(argv)
    except SystemExit as exc:  # argparse's usage error
        status = exc.code
    assert status == 2
    err = capsys.readouterr().err
    assert f"minority {' '.join(command)}: error: " in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_output_directories_are_created(tmp_path, capsys):
    """Each command writes into a directory that is not there yet (the quick ones here; the
    others in their own tests: log repair in test_log_repair, report score in test_score)."""
    from conftest import free_port

    out = tmp_path / "a" / "b"
    assert main(["deploy", "acl", "--run", "r", "-o", str(out / "acl.json")]) == 0
    assert main(["record", "--listen", f"tcp/127.0.0.1:{free_port()}", "--duration", "1",
                 "--quiet", "-o", str(out / "rec" / "x.mcap")]) == 0
    assert main(["sim", "tiny", "--no-publish", "--quiet", "-o", str(out / "sim" / "t.h5")]) == 0
    assert main(["oracle", "spec", str(out / "sim" / "t.h5"), "-o",
                 str(out / "spec" / "spec.json")]) == 0
    assert all((out / f).is_file() for f in ("acl.json", "rec/x.mcap", "sim/t.h5",
                                             "spec/spec.json"))


def test_oracle_spec_is_for_the_run_id_the_sim_uses(tmp_path, capsys):
    """A rollout names its scene file; the spec's default run is what `minority sim` of that
    scene calls its run (the scene's name, here not its file name)."""
    from minority.gns.export import write_hdf5
    from minority.protocol.spec import Spec
    from minority.sim.scene import builtin_scene_path

    scene = tmp_path / "file_name.toml"
    scene.write_text(builtin_scene_path("tiny").read_text().replace('name = "tiny"',
                                                                     'name = "scene_name"'))
    assert main(["sim", str(scene), "--no-publish", "--quiet", "-o", str(tmp_path / "run.h5")]) == 0
    with h5py.File(tmp_path / "run.h5") as f:
        sim_run = f.attrs["scene_name"]  # the run id the sim uses without --run
        positions, interval = f["positions"][:], float(f.attrs["output_interval_s"])
        attrs = {"scene": str(scene), "checkpoint": "none", "bounds_m": f.attrs["bounds_m"],
                 "particle_spacing_m": float(f.attrs["particle_spacing_m"])}
    write_hdf5(tmp_path / "rollout.h5", positions, interval, attrs=attrs)
    assert main(["oracle", "spec", str(tmp_path / "rollout.h5"), "-o", str(tmp_path / "s.json")]) == 0
    assert sim_run == "scene_name" and Spec.load(tmp_path / "s.json").run == sim_run
    # the sim's own trajectory read as a rollout carries the run id itself
    assert main(["oracle", "spec", str(tmp_path / "run.h5"), "-o", str(tmp_path / "t.json")]) == 0
    assert Spec.load(tmp_path / "t.json").run == sim_run
    # a rollout whose scene is gone: the run id must be given
    shutil.move(scene, tmp_path / "gone.toml")
    assert main(["oracle", "spec", str(tmp_path / "rollout.h5"), "-o", str(tmp_path / "u.json")]) == 2
    assert "pass --run" in capsys.readouterr().err and not (tmp_path / "u.json").exists()


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"minority {version()}" != "minority unknown"


@pytest.mark.parametrize("argv", [["--help"], ["oracle", "--help"]], ids=" ".join)
def test_the_help_lists_every_command_and_every_oracle_step(argv, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    text = " ".join(capsys.readouterr().out.split())
    names = {name for (name, *_) in COMMANDS} if argv == ["--help"] else set()
    assert all(name in text for name in names | set(STEPS))
    assert set(STEPS) == {step for (first, *rest) in COMMANDS if first == "oracle" and rest
                          for step in rest}
