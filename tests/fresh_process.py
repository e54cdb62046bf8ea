"""What a fresh interpreter imports: the import-cost tests' one helper."""
from __future__ import annotations

import ast
import subprocess
import sys
from typing import Sequence


def modules_after(code: str, names: Sequence[str]) -> list[str]:
    """Which of the modules ``names`` a fresh interpreter holds after running
    ``code`` (sorted; its last stdout line)."""
    return last_literal(f"{code}\nimport sys\n"
                        f"print(sorted(m for m in {tuple(names)!r} if m in sys.modules))")


def last_literal(code: str):
    """The last line ``code`` prints in a fresh interpreter, as a Python literal."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return ast.literal_eval(out.stdout.strip().splitlines()[-1])


def cli_call(*args, exits: bool = False) -> str:
    """Code running ``seanv-analyze args`` in-process (``exits``: the
    command ends in SystemExit, as ``--help`` does, which is caught)."""
    call = f"cli.main(args={[str(a) for a in args]!r}, standalone_mode=False)"
    if exits:
        call = f"try:\n    {call}\nexcept SystemExit:\n    pass"
    return f"from seanv_analysis.cli import cli\n{call}"
