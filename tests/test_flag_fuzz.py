"""Property-based fuzz of the command line: whatever flags and values a user types, every
subcommand either refuses them in one line naming what is wrong (exit 2; argparse's usage for an
unknown flag or a value of the wrong type) or accepts them and starts its work — never a
traceback. The commands run in this process with their work (the first heavy call of each:
meshing, a dataset, a palpation, a study) replaced by a sentinel, so that what is checked is
everything a command does before its work; a watchdog stops any example that gets further."""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import signal
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jointsim.cli.main import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


class Reached(BaseException):
    """The command accepted its arguments and began its work (a BaseException: main's one-line
    error handler must not take it for a refusal)."""


# each command's first heavy call, where it is looked up at run time
WORK = [
    ("jointsim.dataset", "generate_dataset"), ("jointsim.design.study", "run_design"), ("jointsim.studies.rest", "read_at_rest"),
    ("jointsim.studies.indentation", "indentation_sweep"), ("jointsim.instrument", "deployed_chamber"),
    ("jointsim.palpation.job", "palpate"), ("jointsim.studies.protocol_study", "run_protocol_study"),
    ("jointsim.cli.stiffness_study", "run_study"), ("jointsim.calibration", "calibrate"), ("jointsim.studies.measured", "image_frames"),
    ("jointsim.eit.fit", "fit_reference"), ("jointsim.instrument", "Instrument"),
]
WATCHDOG_S = 60


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    p = build_parser()
    return next(a for a in p._actions if isinstance(a, argparse._SubParsersAction)).choices


SUB = _subparsers()
NUMBERS = ["0", "1", "-1", "3", "2.5", "-0.5", "1e9", "-1e20", "1e400", "nan", "inf", "-inf", "18446744073709551616", "16", "0.001"]
WORDS = ["", "abc", "auto", "cpu", "cuda:7", "superlu", "cudss", "tikhonov", "position", "force", "none", "test", "dataset",
         "paper", "1,2,3", "3,-1", "1,,2", "7.5,15", "0,0", "1;2", "tcp://127.0.0.1:1"]


def _paths(tmp: Path) -> list[str]:
    (tmp / "a_folder").mkdir(exist_ok=True)
    (tmp / "text.txt").write_text("not a store\n")
    (tmp / "bad.toml").write_text("[electrodes\ncount = \n")
    (tmp / "empty.toml").write_text("")
    (tmp / "binary.toml").write_bytes(b"\xff\xfe\x00\x01\x80")
    return [str(tmp / "out"), str(tmp / "a_folder"), str(tmp / "text.txt"), str(tmp / "missing" / "x.h5"), str(tmp / "bad.toml"),
            str(tmp / "empty.toml"), str(tmp / "binary.toml"), "/proc/jointsim/out", "/dev/null", str(tmp / "text.txt" / "under"),
            str(ROOT / "scenes" / "paper_sensor.toml"), str(tmp / "new.h5")]


@st.composite
def command_lines(draw, tmp: Path) -> list[str]:
    name = draw(st.sampled_from(sorted(SUB)))
    parser = SUB[name]
    paths = _paths(tmp)
    argv = [name]
    actions = [a for a in parser._actions if a.dest != "help"]
    for a in draw(st.lists(st.sampled_from(actions), max_size=5, unique_by=id)):
        if not a.option_strings:  # a positional: a scene, a dataset, design scenes
            argv += draw(st.lists(st.sampled_from(paths), min_size=0 if a.nargs in ("?", "*") else 1, max_size=2))
            continue
        flag = draw(st.sampled_from(a.option_strings))
        if a.nargs == 0:  # store_true, --x / --no-x
            argv.append(flag)
            continue
        if a.type is Path:
            pool = paths
        elif a.type in (int, float):
            pool = NUMBERS
        else:
            pool = WORDS + NUMBERS + list(a.choices or [])
        argv += [flag, draw(st.sampled_from(pool))]
    # an output under the example's folder unless the draw named one: nothing lands in the repo
    if "--out" in [x for a in actions for x in a.option_strings] and "--out" not in argv:
        argv += ["--out", str(tmp / "out" / ("d.h5" if name == "dataset" else "o"))]
    return argv


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("flag-fuzz")


@contextlib.contextmanager
def _work_replaced():
    import importlib

    saved = []
    def reached(*a, **k):
        raise Reached()
    for mod, name in WORK:
        m = importlib.import_module(mod)
        saved.append((m, name, getattr(m, name)))
        setattr(m, name, reached)
    env = dict(os.environ)

    def watchdog(signum, frame):
        raise Reached()
    old = signal.signal(signal.SIGALRM, watchdog)
    signal.alarm(WATCHDOG_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
        for m, name, f in saved:
            setattr(m, name, f)
        os.environ.clear()
        os.environ.update(env)  # a --solver sets JOINTSIM_SOLVER for the run's workers


@pytest.mark.parametrize("seed", [0])
def test_any_command_line_is_refused_in_one_line_or_accepted(fuzz_dir, seed):
    @settings(max_examples=300, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
    @given(command_lines(fuzz_dir))
    def check(argv):
        err = io.StringIO()
        with _work_replaced(), contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                rc = main(argv)
            except Reached:
                return
            except SystemExit as e:  # argparse: the subcommand's usage and one error line
                assert e.code == 2, (argv, err.getvalue())
                assert err.getvalue().strip().splitlines()[-1].startswith(f"jointsim {argv[0]}: error: "), (argv, err.getvalue())
                return
        lines = [x for x in err.getvalue().strip().splitlines() if ": warning: " not in x]
        assert rc == 2 and len(lines) == 1 and lines[0].startswith(f"jointsim {argv[0]}: error: "), (argv, rc, err.getvalue())

    check()
