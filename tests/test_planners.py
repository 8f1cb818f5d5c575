import sys

import numpy as np
import pytest

from mitsuba_active.errors import UserError
from mitsuba_active.planners import PlanningState, make_planner, names
from mitsuba_active.planners.fisher import greedy_fisher
from mitsuba_active.planners.rfe import rfe_scores
from mitsuba_active.rigs import fibonacci_sphere

CANDS = fibonacci_sphere(12, [0, 0, 0], 2.0, 40.0, 8, 8)


def test_registry_and_unknown_names():
    assert set(names()) == {"random", "even", "rfe", "fisher", "coverage", "variational", "hybrid"}
    with pytest.raises(UserError, match="unknown planner"):
        make_planner("oracle")
    # Names in any case; a mistyped one is answered with the nearest.
    assert make_planner("RFE").name == "rfe" and make_planner("Even").name == "even"
    with pytest.raises(UserError, match=r"unknown planner 'rfr' \(did you mean 'rfe'\?\)"):
        make_planner("rfr")
    with pytest.raises(UserError):
        make_planner("rfe", form="median")


def test_planner_options_are_checked():
    for bad in (dict(lam="abc"), dict(lam=0), dict(probes=2.7), dict(probes=0), dict(probes=True)):
        with pytest.raises(UserError, match="fisher"):
            make_planner("fisher", **bad)
    assert make_planner("fisher", lam=1, probes=3).options() == {"lam": 1.0, "probes": 3}


def test_greedy_top_skips_unscored_candidates():
    from mitsuba_active.planners.base import greedy_top

    scores = np.array([1.0, np.inf, 0.5, np.nan, 0.2])
    allowed = np.array([True, False, True, True, True])
    assert greedy_top(scores, allowed, 3) == [0, 2, 4]
    assert greedy_top(np.array([0.1, np.inf, 0.1]), np.ones(3, bool), 3) == [1, 0, 2]
    with pytest.raises(UserError, match="could not be scored"):
        greedy_top(scores, allowed, 4)


def test_even_never_repeats_and_runs_out():
    planner, state = make_planner("even"), PlanningState(CANDS, [], rng=np.random.default_rng(0))
    for _ in range(4):
        picks, _ = planner.select(state, 3)
        state.captured.extend(picks)
    assert sorted(state.captured) == list(range(12))
    with pytest.raises(UserError):
        planner.select(state, 1)


def test_random_samples_with_replacement_uniformly():
    planner, state = make_planner("random"), PlanningState(CANDS, [0, 1, 2], rng=np.random.default_rng(1))
    picks, _ = planner.select(state, 2400)
    counts = np.bincount(picks, minlength=12)
    assert len(set(picks)) < len(picks)  # repeats happen
    assert counts[:3].min() > 0  # captured views can be drawn again
    assert np.abs(counts / 200.0 - 1.0).max() < 0.3


def test_coverage_picks_the_direction_farthest_from_captured():
    planner = make_planner("coverage")
    state = PlanningState(CANDS, [0], rng=np.random.default_rng(0))
    picks, scores = planner.select(state, 1)
    dirs = np.stack([c.forward for c in CANDS])
    assert picks[0] == int(np.argmin(dirs @ dirs[0]))
    assert scores[0] == 0.0


def test_rfe_score_forms():
    v = np.zeros((3, 4, 3))
    v[1] = 0.01
    v[2, 0] = 0.5  # one very uncertain ray
    assert rfe_scores(v, "sum").argmax() == 2
    assert rfe_scores(v, "log").argmax() == 1  # log form rewards broad uncertainty


def test_fisher_choice_is_invariant_to_rescaling():
    rng = np.random.default_rng(3)
    h_c, h_t = rng.random((8, 50)) ** 3, rng.random(50)
    allowed = np.ones(8, bool)
    allowed[2] = False
    picks, scores = greedy_fisher(h_c, h_t, allowed, 3)
    picks2, scores2 = greedy_fisher(1e6 * h_c, 1e6 * h_t, allowed, 3)
    assert picks == picks2 and 2 not in picks
    assert np.allclose(scores, scores2)



def test_fisher_batches_fold_each_pick_into_the_training_information():
    h = np.zeros((3, 4))
    h[0, :2] = h[1, :2] = 1.0  # two views that inform the same parameters
    h[2, 2:] = 0.8  # a slightly weaker view of other parameters
    picks, scores = greedy_fisher(h, np.zeros(4), np.ones(3, bool), 2)
    assert scores.argmax() in (0, 1) and picks[0] == 0
    assert picks[1] == 2  # not the duplicate, whose information is already counted


@pytest.mark.parametrize("name", ["even", "coverage", "fisher", "hybrid"])
def test_a_batch_larger_than_the_views_left_names_both_counts(name):
    # fisher is refused before it computes any Fisher information (no ensemble is needed to say so).
    from types import SimpleNamespace

    rays = np.zeros((len(CANDS), 1, 3), np.float32)
    state = PlanningState(CANDS, list(range(11)), ensemble=SimpleNamespace(n_members=1), candidate_rays=(rays, rays),
                          rng=np.random.default_rng(0))
    with pytest.raises(UserError, match="only 1 candidate views are left to choose from, asked for 2"):
        make_planner(name).select(state, 2)


@pytest.mark.parametrize("name", ["rfe", "fisher", "hybrid"])
def test_scoring_planners_say_what_the_state_lacks(name):
    from types import SimpleNamespace

    with pytest.raises(ValueError, match=f"the {name} planner .* has no ensemble and no candidate_rays"):
        make_planner(name).select(PlanningState(CANDS, [0]), 1)
    rays = np.zeros((len(CANDS), 4, 3), np.float32)
    for bad, got in (((list(rays), rays), "'list'"), ((rays.reshape(-1, 3), rays.reshape(-1, 3)), "\\(48, 3\\)"),
                     ((rays[:3], rays[:3]), "\\(3, 4, 3\\)"), (rays, "ndarray")):
        state = PlanningState(CANDS, [0], ensemble=SimpleNamespace(n_members=2), candidate_rays=bad)
        with pytest.raises(ValueError, match=f"needs candidate_rays = \\(origins, directions\\), two numpy arrays "
                                             f"of shape \\(C, R, 3\\) for the C = 12 candidates, got .*({got})"):
            make_planner(name).select(state, 1)


def test_a_planning_state_without_a_generator_repeats_its_picks():
    picks = [make_planner(name).select(PlanningState(CANDS, [0]), 2)[0] for name in ("even", "random") for _ in "ab"]
    assert picks[0] == picks[1] and picks[2] == picks[3]
    # Its stream is a run's planner stream (seed 0), not the one env.reset(seed=0) draws the initial views from.
    from mitsuba_active.planners import planner_rng

    state_draw = PlanningState(CANDS, [0]).rng.random(4)
    assert np.array_equal(state_draw, planner_rng(0).random(4))
    assert not np.allclose(state_draw, np.random.default_rng(0).random(4))
    # Nor the stream of any ensemble member's initial features.
    from mitsuba_active.field.config import MAX_MEMBERS
    from mitsuba_active.field.ensemble import _member_seeds

    for member in _member_seeds(0, MAX_MEMBERS):
        assert not np.allclose(state_draw, np.random.default_rng(member).random(4))


def test_variational_refuses_a_plain_ensemble():
    """A one-member ensemble has no spread to score: every candidate would score 0."""
    from mitsuba_active.field import Ensemble, FieldConfig
    from mitsuba_active.run import sparse_candidate_rays

    ens = Ensemble([-1] * 3, [1] * 3, n_members=1, config=FieldConfig(n_levels=1, log2_table_size=10), seed=0)
    state = PlanningState(CANDS, [0], ens, sparse_candidate_rays(CANDS, 4, 0))
    with pytest.raises(TypeError, match="the variational planner scores with a VariationalField .*, got Ensemble"):
        make_planner("variational").select(state, 1)


def test_greedy_top_and_planner_names_say_what_is_wrong():
    from mitsuba_active.planners import greedy_top
    from mitsuba_active.planners.rfe import RFEPlanner

    with pytest.raises(ValueError, match=r"scores and allowed must both be \(C,\) arrays.*\(2,\) and \(3,\)"):
        greedy_top([0.1, 0.5], np.array([1, 1, 1]), 1)
    with pytest.raises(UserError, match="got <class .*RFEPlanner'>; register RFEPlanner with @register"):
        make_planner(RFEPlanner)


PLANNER_FILE = '''
import numpy as np
from mitsuba_active.planners import Planner, greedy_top, unseen


class Last(Planner):
    """Picks the unseen candidates with the highest indices."""

    def __init__(self, offset: int = 0):
        if offset < 0:
            raise ValueError("offset must be >= 0")
        self.offset = offset

    def options(self):
        return {"offset": self.offset}

    def select(self, state, batch):
        scores = np.arange(len(state.candidates), dtype=float) + self.offset
        return greedy_top(scores, unseen(state), batch), scores


def helper():
    pass
'''


def test_a_planner_of_ones_own_by_reference(tmp_path, monkeypatch):
    import hashlib

    from mitsuba_active.planners import planner_label
    from mitsuba_active.planners.base import planner_digest, resolve_reference

    (tmp_path / "mine.py").write_text(PLANNER_FILE)
    monkeypatch.chdir(tmp_path)
    planner = make_planner("mine.py:Last", offset=2)
    assert planner.options() == {"offset": 2} and planner.name == "mine.py:Last"
    assert planner.select(PlanningState(CANDS, [11]), 2)[0] == [10, 9]
    ref = resolve_reference("mine.py:Last")
    assert ref == f"{tmp_path / 'mine.py'}:Last" and planner_label(ref) == "mine.py:Last"
    assert resolve_reference("rfe") == "rfe" and resolve_reference("pkg.mod:Cls") == "pkg.mod:Cls"
    assert planner_digest(ref) == hashlib.sha256(PLANNER_FILE.encode()).hexdigest()
    assert planner_digest("rfe") is None
    with pytest.raises(UserError, match="bad option for planner 'mine.py:Last': offset must be >= 0"):
        make_planner("mine.py:Last", offset=-1)
    with pytest.raises(UserError, match="unknown option offs \\(it takes offset\\)"):
        make_planner("mine.py:Last", offs=1)


@pytest.mark.parametrize("text, ref, message", [
    (PLANNER_FILE, "mine.py:First", "mine.py has no class 'First'; it defines Last"),
    (PLANNER_FILE, "mine.py:helper", "mine.py:helper is not a planner: a planner is a subclass of"),
    (PLANNER_FILE, "other.py:Last", "planner file not found: .*other.py"),
    ("import numpy\n\nx = 1 / 0\n", "mine.py:Last", "mine.py: ZeroDivisionError: division by zero \\(line 3\\)"),
    ("def f(:\n", "mine.py:Last", "mine.py: SyntaxError: invalid syntax \\(line 1\\)$"),
    (PLANNER_FILE, "no_such_module_here:Last", "no module named 'no_such_module_here' for a planner"),
    (PLANNER_FILE, "../run.sh:Last", "'../run.sh' is neither a planner file \\(FILE.py:CLASS\\) nor a module"),
    ("raise ValueError('first\\nsecond')\n", "mine.py:Last", "ValueError: first second \\(line 1\\)"),
    # A script's habit, which would otherwise end the command silently with exit code 0.
    ("import sys\nsys.exit(0)\n", "mine.py:Last", "mine.py: SystemExit: 0 \\(line 2\\)"),
    ("import helper_with_a_typo\n", "mine.py:Last", "ModuleNotFoundError: .*helper_with_a_typo.* \\(line 1\\)"),
    ("import broken_helper\n", "mine.py:Last",
     "mine.py: SyntaxError: '\\(' was never closed \\(broken_helper.py, line 3\\) \\(line 1\\)"),
    ("from mitsuba_active.planners import Planner\nclass Last(Planner):\n    def choose(self, state, batch):\n"
     "        return [0], None\n", "mine.py:Last", "mine.py:Last has no select\\(state, batch\\) method"),
])
def test_a_bad_planner_reference_is_one_line(tmp_path, monkeypatch, text, ref, message):
    (tmp_path / "mine.py").write_text(text)
    (tmp_path / "broken_helper.py").write_text("\n\nx = (\n")  # its own error is not the planner file's line 3
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match=message) as info:
        make_planner(ref)
    assert "\n" not in str(info.value)


def test_planner_options_may_be_keyword_only(tmp_path):
    (tmp_path / "kw.py").write_text(
        "from mitsuba_active.planners import Planner\n"
        "class K(Planner):\n"
        "    def __init__(self, *, power=1.0):\n"
        "        if power < 0:\n"
        "            raise ValueError('power must be >= 0')\n"
        "    def select(self, state, batch):\n"
        "        return [0], None\n")
    with pytest.raises(UserError, match="'kw.py:K': power must be >= 0 \\(it takes power\\)"):
        make_planner(f"{tmp_path / 'kw.py'}:K", power=-1)
    with pytest.raises(UserError, match="unknown option pow \\(it takes power\\)"):
        make_planner(f"{tmp_path / 'kw.py'}:K", pow=1)
    (tmp_path / "any.py").write_text(
        "from mitsuba_active.planners import Planner\n"
        "class A(Planner):\n"
        "    def __init__(self, **options):\n"
        "        raise ValueError(f'no {sorted(options)}')\n"
        "    def select(self, state, batch):\n"
        "        return [0], None\n")
    with pytest.raises(UserError, match="'any.py:A': no \\['x'\\]$"):  # it takes any name: its own message
        make_planner(f"{tmp_path / 'any.py'}:A", x=1)
    with pytest.raises(UserError, match="no \\['name'\\]$"):  # an option may be called name
        make_planner(f"{tmp_path / 'any.py'}:A", name="x")


def test_a_planner_module_and_the_files_beside_a_planner_import(tmp_path, monkeypatch):
    import hashlib

    from mitsuba_active.planners.base import planner_digest

    (tmp_path / "helper_beside.py").write_text(PLANNER_FILE)
    (tmp_path / "uses_helper.py").write_text("from helper_beside import Last as Beside\n")
    planner = make_planner(f"{tmp_path / 'uses_helper.py'}:Beside")  # not the current folder's
    assert planner.select(PlanningState(CANDS, []), 1)[0] == [11]
    (tmp_path / "planner_module_here.py").write_text(PLANNER_FILE)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert make_planner("planner_module_here:Last", offset=3).options() == {"offset": 3}
    assert planner_digest("planner_module_here:Last") == hashlib.sha256(PLANNER_FILE.encode()).hexdigest()


def test_registering_a_planner_by_name():
    from mitsuba_active.planners import Planner, register
    from mitsuba_active.planners.base import REGISTRY

    class Mine(Planner):
        name = "mine_for_a_test"

        def select(self, state, batch):
            return [1], None

    try:
        register(Mine)
        assert make_planner("mine_for_a_test").select(PlanningState(CANDS, []), 1) == ([1], None)
        # The same class defined again (a reloaded module) takes its name back; another class does not.
        register(type("Mine", (Planner,), {"name": "mine_for_a_test", "__module__": Mine.__module__,
                                           "__qualname__": Mine.__qualname__}))
        with pytest.raises(UserError, match=r"'mine_for_a_test' is the name of the planner .*Mine already"):
            register(type("Yours", (Planner,), {"name": "mine_for_a_test"}))
    finally:
        REGISTRY.pop("mine_for_a_test", None)
    with pytest.raises(UserError, match="give Nameless a name"):
        register(type("Nameless", (Planner,), {}))
    assert "planner" not in REGISTRY
    # Names are looked up in any case: one that differs from another only in case is ambiguous.
    for name, message in (("rfe", "one of mitsuba-active's planners"), ("a:b", "without ':'"),
                          ("RFE", r"'RFE' differs from the name of the planner RFEPlanner \('rfe'\) only in case")):
        with pytest.raises(UserError, match=message):
            register(type("Other", (Mine,), {"name": name}))
    assert REGISTRY["rfe"].__name__ == "RFEPlanner"


def test_a_file_that_registers_a_planner_can_also_be_named_as_a_file(tmp_path, monkeypatch):
    from mitsuba_active.planners.base import REGISTRY

    (tmp_path / "registering_planners.py").write_text(
        "from mitsuba_active.planners import Planner, register\n\n"
        "@register\nclass Sweep(Planner):\n    name = 'sweep_for_a_test'\n\n"
        "    def select(self, state, batch):\n        return [0], None\n\n"
        "class Other(Planner):\n    def select(self, state, batch):\n        return [1], None\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        import registering_planners  # noqa: F401  (registers 'sweep_for_a_test')

        # The same file loaded again as FILE.py:CLASS defines the same classes, not rivals.
        assert make_planner(f"{tmp_path / 'registering_planners.py'}:Other").select(None, 1) == ([1], None)
        assert make_planner("sweep_for_a_test").select(None, 1) == ([0], None)
    finally:
        REGISTRY.pop("sweep_for_a_test", None)
        sys.modules.pop("registering_planners", None)


@pytest.mark.parametrize("answer, message", [
    (([12], None), "picked \\[12\\]"),
    (([0, 1], None), "picked \\[0, 1\\]"),
    (([1.0], None), "picked \\[1.0\\]"),
    ([3], "answered list"),
    (([3], np.zeros(5)), "gave scores of shape \\(5,\\)"),
    (([3], [[1, 2], [3]]), "answered"),
])
def test_a_planners_answer_is_checked(answer, message):
    from mitsuba_active.planners import Planner

    class Odd(Planner):
        name = "odd"

        def select(self, state, batch):
            return answer

    expected = "must return \\(indices, scores\\): 1 candidate indices \\(whole numbers\\) in \\[0, 12\\)"
    with pytest.raises(UserError, match=f"the odd planner {message}.*{expected}"):
        Odd().checked_select(PlanningState(CANDS, []), 1)
    picks, scores = make_planner("coverage").checked_select(PlanningState(CANDS, [0]), 2)
    assert len(picks) == 2 and all(type(i) is int for i in picks) and scores.dtype == np.float64


def test_a_planner_that_changes_the_state_in_place_changes_nothing_of_the_run():
    from mitsuba_active.planners import Planner

    class Greedy(Planner):  # keeps its picks in the state's own lists
        name = "greedy"

        def select(self, state, batch):
            state.captured.append(5)
            state.candidates.pop()
            return [5], None

    state = PlanningState(CANDS, [0, 1])
    assert Greedy().checked_select(state, 1) == ([5], None)
    assert state.captured == [0, 1] and len(state.candidates) == len(CANDS) == 12
