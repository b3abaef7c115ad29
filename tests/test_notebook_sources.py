"""The chapters' code as Python reads it, without running it: a cell that compiles with a warning on one Python
(an invalid escape such as ``"$V^\\star$"`` is a DeprecationWarning on 3.11 and a SyntaxWarning, printed into
the cell's output, from 3.12) would make the outputs that nbval compares depend on the computer."""

import json
import warnings
from pathlib import Path

import pytest

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_every_code_cell_compiles_without_a_warning(path):
    cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
    problems = []
    for k, cell in enumerate(cells):
        if cell["cell_type"] != "code":
            continue
        source = "".join(cell["source"])
        code = "\n".join(line for line in source.splitlines() if not line.lstrip().startswith(("%", "!")))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            try:
                compile(code, f"{path.name}, cell {k} ({cell.get('id')})", "exec")
            except (SyntaxError, SyntaxWarning, DeprecationWarning) as err:
                problems.append(f"cell {k} ({cell.get('id')}): {err}")
    assert not problems, f"{path.name}:\n  " + "\n  ".join(problems)
