"""benchmarks/brax_comparison.py's printed table: a ratio to Brax positional is starred unless both
of its numbers were measured in the same run of the script (the results file merges runs)."""

from benchmark_scripts import BENCHMARKS, load

brax_comparison = load("brax_comparison", BENCHMARKS / "brax_comparison.py")


def _engine(rate_batch_1: float, rate_batch_16: float, grad_compile: float, runs: tuple) -> dict:
    return {
        "throughput": [
            {"batch": 1, "steps_per_s": rate_batch_1, "run": runs[0]},
            {"batch": 16, "steps_per_s": rate_batch_16, "run": runs[1]},
        ],
        "compile": {"grad_rollout100_s": grad_compile, "run": runs[2]},
    }


def _rows(capsys) -> dict[tuple[str, str], list[str]]:
    """(engine, batch) -> the row's columns after them."""
    lines = capsys.readouterr().out.splitlines()
    return {tuple(line.split()[:2]): line.split()[2:] for line in lines if line.startswith(("dbdjax", "brax"))}


def test_ratios_of_numbers_from_one_run_are_plain_and_from_two_runs_starred(capsys):
    per_engine = {
        "dbdjax-dbd": _engine(2000.0, 8000.0, 60.0, runs=(3, 2, 3)),
        "brax-positional": _engine(10000.0, 40000.0, 30.0, runs=(3, 3, 3)),
    }
    brax_comparison.print_table("humanoid", per_engine)
    rows = _rows(capsys)
    # steps/s, its ratio, grad compile s, its ratio
    assert rows[("dbdjax-dbd", "1")] == ["2000", "0.20", "60.0", "2.00"]
    assert rows[("dbdjax-dbd", "16")] == ["8000", "0.20*", "60.0", "2.00"]
    assert rows[("brax-positional", "1")] == ["10000", "1.00", "30.0", "1.00"]


def test_a_number_from_before_runs_were_recorded_stars_its_ratio_and_the_footnote_says_why(capsys):
    per_engine = {
        "dbdjax-dbd": _engine(2000.0, 8000.0, 60.0, runs=(0, 0, 0)),
        "brax-positional": _engine(10000.0, 40000.0, 30.0, runs=(0, 0, 0)),
    }
    del per_engine["dbdjax-dbd"]["compile"]["run"]
    brax_comparison.print_table("humanoid", per_engine)
    out = capsys.readouterr().out
    dbd_row = next(line for line in out.splitlines() if line.startswith("dbdjax-dbd"))
    assert dbd_row.split()[3:] == ["0.20", "60.0", "2.00*"]
    assert "* of numbers from different runs" in out


def test_a_table_of_one_run_has_no_footnote(capsys):
    per_engine = {
        "dbdjax-dbd": _engine(2000.0, 8000.0, 60.0, runs=(1, 1, 1)),
        "brax-positional": _engine(10000.0, 40000.0, 30.0, runs=(1, 1, 1)),
    }
    brax_comparison.print_table("ant", per_engine)
    out = capsys.readouterr().out
    assert "*" not in out
