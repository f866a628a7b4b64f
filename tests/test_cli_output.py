"""An output the command line cannot write is refused before any work, in one line naming --out,
the path and why (exit 2): under a file, a file where a folder is wanted and the reverse, a
virtual or device file system."""

import pytest

from jointsim.cli.main import SUBCOMMANDS, main

WRITERS = sorted(name for name, mod in SUBCOMMANDS.items() if getattr(mod, "OUTPUT", None))


def _bad_outputs(tmp_path, kind):
    plain = tmp_path / "plain.txt"
    plain.write_text("not a folder\n")
    cases = {"under a file": plain / "sub", "a virtual file system": "/proc/jointsim-out", "a device": "/dev/null"}
    cases.update({"a file": plain} if kind == "folder" else {"a folder": tmp_path})
    return cases


def test_every_command_that_writes_says_what_its_output_is():
    assert set(WRITERS) == {"calibrate", "dataset", "design-study", "forward", "indent", "palpate", "protocol-study",
                            "stiffness-study"}


@pytest.mark.parametrize("command", WRITERS)
def test_an_output_that_cannot_be_written_is_refused_in_one_line(command, tmp_path, capsys):
    kind = SUBCOMMANDS[command].OUTPUT
    for why, out in _bad_outputs(tmp_path, kind).items():
        required = {"calibrate": ["missing.h5"], "dataset": ["--n", "3"]}.get(command, [])
        args = [command, *required, "--out", str(out)]
        assert main(args) == 2, why
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"jointsim {command}: error: --out {out}:"), (why, err)
    assert not list(tmp_path.glob(".jointsim-probe-*"))  # the probe leaves nothing behind
