"""The README's Python example runs as written and prints what the README says it prints; the
README's first-screen figures are the paper's example as `solve` prints it."""

import shutil

from tests.conftest import ROOT

README = (ROOT / "README.md").read_text()


def _blocks(language: str) -> list[str]:
    """The README's fenced blocks of ``language`` ("" for plain ones), in order."""
    blocks, current, kind = [], None, None
    for line in README.splitlines(keepends=True):
        if line.startswith("```"):
            if current is None:
                current, kind = [], line[3:].strip()
            else:
                if kind == language:
                    blocks.append("".join(current))
                current = None
        elif current is not None:
            current.append(line)
    return blocks


def test_the_python_example_prints_what_the_readme_says(tmp_path, monkeypatch, capsys, paper_solve_out):
    """Run as a user runs it from the repository (here in a copy of problems/, in this process);
    its bounds are those `solve` writes for the same file (a copy is the same problem: the
    approximate designs computed for the suite's solve are read back here)."""
    import json

    (code,) = _blocks("python")
    printed = next(b for b in _blocks("") if b.startswith("2 parameters"))
    shutil.copytree(ROOT / "problems", tmp_path / "problems")
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    example = {"__name__": "__main__"}
    exec(compile(code, "README.md", "exec"), example)
    assert capsys.readouterr().out == printed
    assert (tmp_path / "fig1.png").stat().st_size > 10_000 and (tmp_path / "fig1.pdf").exists()
    solved = {(d["criterion"], d["m"]): d for d in json.loads((paper_solve_out / "results.json").read_text())["designs"]}
    for (criterion, m), design in example["campaign"].designs.items():
        assert design.bound.value == solved[criterion, m]["bound"]["value"]


def test_the_first_screen_table_is_the_paper_example_as_solve_finds_it(paper_solve_out):
    """The table's test-pose and D rows are the designs `solve` finds (the suite's run: fewer
    starts, the same optima), and the paper's Table 4 to its printed digits (mm)."""
    import json

    table = next(b for b in _blocks("") if b.startswith("max over test poses"))
    rows = {ln.split()[0]: [float(v) for v in ln.split()[1:]] for ln in table.splitlines()[3:7]}
    found = {(d["criterion"], d["m"]): d["max_rms_error_m"] * 1e3
             for d in json.loads((paper_solve_out / "results.json").read_text())["designs"]}
    for c in ("test-pose", "D"):
        assert [round(found[c, m], 4) for m in (1, 5)] == rows[c]
    assert [round(v, 3) for v in rows["test-pose"]] == [0.136, 0.055]
    assert [round(v, 3) for v in rows["D"]] == [0.170, 0.069]
    assert round(rows["E"][0], 3) == 0.240
