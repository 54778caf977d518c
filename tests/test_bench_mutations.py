"""The mutation check's machinery (``python -m beavr_sim.bench mutations``) on a tiny fake
repository: a planted bug its test catches, one it does not, a stale snippet, a test selection
that fails with no bug planted; the real list is well formed."""

from __future__ import annotations

import sys

import pytest

from beavr_sim.bench import mutations
from beavr_sim.bench.mutations import MUTATIONS, Mutation, run, score, table

RULE = "def allowed(speed: float) -> bool:\n    return speed <= 1.0\n"
TEST = "from pkg.rule import allowed\n\n\ndef test_too_fast_is_refused():\n    assert not allowed(2.0)\n"


@pytest.fixture
def repo(tmp_path):
    root = tmp_path / "repo"
    (root / "pkg").mkdir(parents=True)
    (root / "pkg" / "__init__.py").write_text("")
    (root / "pkg" / "rule.py").write_text(RULE)
    (root / "tests").mkdir()
    (root / "tests" / "test_rule.py").write_text(TEST)
    (root / "tests" / "test_broken.py").write_text("def test_broken():\n    assert False\n")
    return root


def test_caught_survived_stale_and_a_failing_baseline(repo):
    tests = ("tests/test_rule.py",)
    planted = [
        Mutation("looser", "speed cap", "pkg/rule.py", "speed <= 1.0", "speed <= 10.0", tests),
        Mutation("same", "speed cap", "pkg/rule.py", "speed <= 1.0", "(speed <= 1.0)", tests),
        Mutation("moved", "speed cap", "pkg/rule.py", "speed < 1.0", "speed < 10.0", tests),
        Mutation("gone", "speed cap", "pkg/nope.py", "x", "y", tests),
        Mutation("broken", "speed cap", "pkg/rule.py", "1.0", "2.0", ("tests/test_broken.py",)),
    ]
    seen = []
    quick = {"PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}  # the fake tests need no plugins
    results = run(
        planted, repo, python=sys.executable, timeout_s=120, progress=seen.append, extra_env=quick
    )
    status = {r.name: r.status for r in results}
    assert status == {
        "looser": "caught",
        "same": "survived",
        "moved": "stale",
        "gone": "stale",
        "broken": "error",
    }
    assert [r.name for r in results][:2] == ["moved", "gone"]  # stale ones first
    assert seen == results
    by_name = {r.name: r for r in results}
    assert "not found in pkg/rule.py" in by_name["moved"].detail
    assert "does not exist" in by_name["gone"].detail
    assert "fail with no bug planted" in by_name["broken"].detail
    assert "test_too_fast_is_refused" in by_name["looser"].detail
    # The repository itself is never touched.
    assert (repo / "pkg" / "rule.py").read_text() == RULE
    assert score(results) == {
        "caught": 1,
        "total": 5,
        "by_status": {"caught": 1, "survived": 1, "stale": 2, "error": 1, "timeout": 0},
    }
    text = table(results)
    assert "| `moved` | speed cap | stale |" in text
    assert text.endswith("caught 1 / 5 (1 survived, 2 stale, 1 error)")


def test_a_snippet_found_twice_is_stale(repo):
    (repo / "pkg" / "rule.py").write_text(RULE + RULE.replace("allowed", "also"))
    m = Mutation("twice", "speed cap", "pkg/rule.py", "speed <= 1.0", "speed <= 9.0", ("x",))
    assert "found 2 times" in mutations.stale(m, repo)


def test_the_safety_mutations_are_well_formed(capsys):
    names = [m.name for m in MUTATIONS]
    assert len(names) == len(set(names)) >= 16
    with pytest.raises(ValueError, match="plants nothing"):
        Mutation("x", "r", "f.py", "a", "a", ("t",))
    assert mutations.main(["--list", "--only", "dataset-discard,guard-velocity"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in out] == ["dataset-discard", "guard-velocity"]
    with pytest.raises(SystemExit):
        mutations.main(["--only", "guard-velocityy"])
    assert "did you mean" in capsys.readouterr().err.lower()
