"""`--help` of every command of the `neumatex` CLI (neumatex_core/cli.py, extract_cli.py) and of `python -m services`
prints its usage and exits 0, with no traceback (a `%` in a help string used to crash argparse)."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys

import pytest

from neumatex_core import cli
from services import __main__ as service_cli

COMMANDS = ["validate", "serve", *cli.CLIENT_COMMANDS, *cli.COMMANDS]
SERVICE_COMMANDS = ["serve", "api", "worker", "create-tenant", "reap", "set-limits"]


def help_of(main: object, argv: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exit_info:
        main(argv)  # type: ignore[operator]
    assert exit_info.value.code == 0, argv
    return out.getvalue()


@pytest.mark.parametrize("command", COMMANDS)
def test_neumatex_command_help(command: str) -> None:
    text = help_of(cli.main, [command, "--help"])
    assert text.startswith("usage: neumatex " + command)


def test_train_basis_help_names_its_percent() -> None:
    assert "1% of it" in help_of(cli.main, ["train-basis", "--help"])


@pytest.mark.parametrize("command", SERVICE_COMMANDS)
def test_service_command_help(command: str) -> None:
    assert help_of(service_cli.main, [command, "--help"]).startswith("usage: python -m services " + command)


def test_installed_entry_point_help_has_no_traceback() -> None:
    r = subprocess.run([sys.executable, "-m", "neumatex_core.cli", "train-basis", "--help"], capture_output=True,
                       text=True, timeout=120)  # fmt: skip
    assert r.returncode == 0 and "Traceback" not in r.stderr and "usage:" in r.stdout, r.stderr
