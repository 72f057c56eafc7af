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


def test_an_engine_measured_at_rest_alone_prints_its_rest_beside_mujocos(capsys):
    per_engine = {
        "dbdjax-dbd-tree": {
            "throughput": [],
            "rest": {"seconds": 10.0, "root_height_m": 0.3619, "energy_rise_second_half_J": 0.0, "run": 2},
        }
    }
    mujoco = {"root_height_m": 0.3618, "settled_after_s": 36.3, "root_height_after_10_s_m": 0.5737, "run": 2}
    brax_comparison.print_table("ant", per_engine, mujoco)
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("dbdjax-dbd-tree"))
    assert "at rest after 10 s: root at 0.362 m (MuJoCo's, settled after 36 s: 0.362 m)" in line
    assert "energy rise in the second half 0.00 J" in line


def test_mujocos_ant_settles_on_its_ankle_limits():
    """The reference the rest task compares with: Brax's ant.xml under zero control creeps down on
    its joint damping (its first step's limit correction swings the ankles to 1.24 rad, past their
    upper bound) and settles after about 36 s with its ankles on their lower bounds (0.524 rad)."""
    rest = brax_comparison.mujoco_rest(brax_comparison.ASSETS / "ant.xml")
    assert abs(rest["root_height_m"] - 0.362) < 0.002
    assert rest["root_height_after_10_s_m"] > 0.55  # still creeping at 10 s
    assert 30 < rest["settled_after_s"] < 45


def test_a_mujoco_rest_that_never_settled_says_so(capsys):
    per_engine = {"dbdjax-dbd": {"throughput": [], "rest": {"seconds": 10.0, "root_height_m": -1.108,
                                                            "energy_rise_second_half_J": -0.01, "run": 2}}}  # fmt: skip
    brax_comparison.print_table("humanoid", per_engine, {"root_height_m": -1.1769, "settled_after_s": None, "run": 2})
    assert "(MuJoCo's had not settled after 120 s: -1.177 m)" in capsys.readouterr().out
