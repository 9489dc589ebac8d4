"""One command-line vocabulary: every subcommand has the shared flags with the same names and metavars,
wrong flag values are blamed on the flag, and ``brdfjax --help`` / ``--version`` load no subcommand stack."""

from __future__ import annotations

import argparse
import subprocess
import sys
import textwrap

import pytest

from brdfjax.cli import COMMANDS, build_parser
from brdfjax.runtime.cli_args import SHARED_FLAGS


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


SUBS = _subparsers()


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings}


def test_every_command_is_in_the_parser():
    assert set(SUBS) == set(COMMANDS)


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_shared_flags_and_metavars(name):
    p = SUBS[name]
    opts = _options(p)
    for flag in SHARED_FLAGS:
        assert flag in opts, f"brdfjax {name} lacks {flag}"
        assert opts[flag].nargs == 0 and opts[flag].help, (name, flag)
    assert opts["--no-figures"].dest == "no_figures"
    # the old spelling still works, hidden from the help
    assert opts["--no-plot"].dest == "no_figures" and opts["--no-plot"].help == argparse.SUPPRESS
    assert "--no-plot" not in p.format_help()
    assert opts["--out"].metavar == "DIR" and opts["--out"].required, name
    positionals = [a for a in p._actions if not a.option_strings]
    assert len(positionals) == 1, name
    if positionals[0].dest == "config":
        assert positionals[0].metavar == "CONFIG", name
    # every option that takes a value shows a metavar or its choices
    for a in p._actions:
        if a.option_strings and a.nargs != 0 and a.help != argparse.SUPPRESS and not isinstance(a, argparse._HelpAction):
            assert a.metavar or a.choices, (name, a.option_strings)


def test_the_same_flag_has_the_same_metavar_on_every_command():
    seen: dict[str, set[str]] = {}
    for p in SUBS.values():
        for flag, a in _options(p).items():
            if a.nargs != 0 and a.metavar:
                seen.setdefault(flag, set()).add(a.metavar)
    assert all(len(v) == 1 for v in seen.values()), {k: v for k, v in seen.items() if len(v) > 1}


def test_sample_help_names_every_sampler():
    text = SUBS["sample"].format_help() + build_parser().format_help()
    assert "emcee" in text and "NUTS" in text


@pytest.mark.parametrize("argv, flag", [
    (["simulate", "--out", "x", "--step", "0"], "--step"),
    (["reduce", "m.toml", "--out", "x", "--step", "-2"], "--step"),
    (["sample", "c.toml", "--out", "x", "--walkers", "0"], "--walkers"),
    (["batch", "s.toml", "--out", "x", "--workers", "zero"], "--workers"),
])
def test_a_bad_flag_value_names_the_flag(argv, flag, capsys):
    with pytest.raises(SystemExit) as e:
        build_parser(argv[0]).parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}" in err and "positive integer" in err, err


def test_top_level_help_and_version_load_no_subcommand_stack():
    code = textwrap.dedent("""
        import sys
        from brdfjax.cli import main
        for argv in (["--help"], ["--version"]):
            try:
                main(argv)
            except SystemExit as e:
                assert e.code == 0, e.code
        heavy = sorted(m for m in ("jax", "numpy", "brdfjax.fit", "brdfjax.sample", "emcee") if m in sys.modules)
        print("HEAVY", heavy)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "HEAVY []" in out, out
    assert "COMMAND" in out and "batch" in out and "brdfjax 0.1.0" in out


def test_a_table_path_that_is_a_directory_gets_its_own_message(tmp_path):
    from brdfjax.fit import FitInputError, read_table

    with pytest.raises(FitInputError, match="is a directory, not a table file"):
        read_table(tmp_path, {"theta_i": 0, "theta_s": 1, "phi_s": 2, "brdf": 3})
    cfg = tmp_path / "fit.toml"
    cfg.write_text(textwrap.dedent(f"""
        [[data.tables]]
        path = "{tmp_path.as_posix()}"
        format = "table"
        columns = {{ theta_i = 0, theta_s = 1, brdf = 2 }}
        [model]
        preset = "solar_cell"
    """))
    proc = subprocess.run([sys.executable, "-m", "brdfjax", "fit", str(cfg), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True)
    assert proc.returncode == 2, proc.stderr
    assert "data.tables[0].path" in proc.stderr and "is a directory" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr


def test_no_progress_silences_progress_lines_but_not_status_lines():
    import io

    from brdfjax.runtime.progress import ProgressLine, make_console

    for no_progress, expect_lines in ((False, True), (True, False)):
        console = make_console(no_progress=no_progress)
        console.file = io.StringIO()
        with ProgressLine(console, "work", 3, min_interval_s=0.0) as bar:
            for i in range(1, 4):
                bar.update(i)
        console.print("status line", markup=False)
        text = console.file.getvalue()
        assert ("work: 3/3" in text) is expect_lines and "status line" in text and "\r" not in text
