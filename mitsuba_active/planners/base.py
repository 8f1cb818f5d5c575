"""The planner interface, the registry by name, and planners of the user's own.

A planner is named by its registered name (``rfe``) or by a reference to a
:class:`Planner` subclass of the user's own: ``path/to/file.py:ClassName``
or ``package.module:ClassName``. References work wherever a name does
(``plan --planner``, suites, :class:`~mitsuba_active.run.RunConfig`), also in
``bench``'s worker processes, which load the class by its reference.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import sys
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..checks import choice_named, is_whole, not_a_file, unknown_choice
from ..errors import UserError
from ..field import Ensemble
from ..imageio_utils import folder_name


#: The spawn key of the planner's random stream: beyond every ensemble member's.
PLANNER_STREAM = 2**31


def planner_rng(seed: int) -> np.random.Generator:
    """The planner's random stream of a run with this seed.

    ``env.reset(seed=seed)`` draws the initial views from the stream of
    ``default_rng(seed)``. The planner must not replay it: ``random`` would
    then re-pick an initial view in about half the runs, wasting a view.
    Nor the streams of the ensemble's members (``spawn_key=(k,)``, k below
    :data:`~mitsuba_active.field.config.MAX_MEMBERS`): a planner's draws would follow
    a member's initial features.
    """
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(PLANNER_STREAM,)))


@dataclass
class PlanningState:
    """What a planner may look at when choosing views.

    Attributes:
        candidates: the candidate :class:`~mitsuba_active.cameras.Camera` list.
        captured: indices of candidates captured so far (repeats possible).
        ensemble: the trained :class:`~mitsuba_active.field.Ensemble`, or None
            for planners that do not need one.
        candidate_rays: ``(origins, directions)``, each (C, R, 3) float32: a
            fixed sparse set of R rays per candidate.
        rng: the run's ``numpy.random.Generator``; when not given,
            ``planner_rng(0)`` (that of a run with seed 0), so that a state
            made anew gives the same picks (each call moves one state's
            stream on, as a run's rounds do).
        out_of_reach: indices of candidates the camera cannot get to (a
            drone's or a base's), which :func:`unseen` leaves out.
        budget: views the run will have captured in all, where the candidates
            are its fixed pool (None: unknown, or candidates that change).
    """

    candidates: list
    captured: list
    ensemble: object = None
    candidate_rays: tuple | None = None
    rng: np.random.Generator = field(default_factory=lambda: planner_rng(0))
    out_of_reach: set = field(default_factory=set)
    budget: int | None = None


def _are_candidate_rays(rays, n_candidates: int) -> bool:
    """Whether ``rays`` is ``(origins, directions)``: two (C, R, 3) numpy arrays for C candidates."""
    if not (isinstance(rays, (tuple, list)) and len(rays) == 2 and all(isinstance(a, np.ndarray) for a in rays)):
        return False
    o, d = rays
    return o.shape == d.shape and o.ndim == 3 and o.shape[0] == n_candidates and o.shape[2] == 3


class Planner:
    """Chooses the next views. Subclasses set ``name`` and implement :meth:`select`."""

    name = "planner"
    needs_ensemble = False
    #: Fewest ensemble members the planner can work with.
    min_members = 1
    #: Most members the planner looks at (None: all); a run trains no more.
    max_members = None

    def make_field(self, bbox_min, bbox_max, n_members: int, config, seed: int):
        """The field a run trains for this planner (with ``needs_ensemble``):
        an :class:`~mitsuba_active.field.Ensemble` of ``n_members``. A run
        resumes with the saved field, read by that field's class's ``load``."""
        return Ensemble(bbox_min, bbox_max, n_members=n_members, config=config, seed=seed)

    def ensemble_size(self, requested: int) -> int:
        """Members to train for a requested ensemble size (``--ensemble``)."""
        return requested if self.max_members is None else min(requested, self.max_members)

    def check_ensemble_size(self, n_members: int) -> None:
        """UserError when an ensemble of ``n_members`` is too small for this planner."""
        if self.needs_ensemble and n_members < self.min_members:
            raise UserError(f"the {self.name} planner needs an ensemble of at least {self.min_members} members "
                            f"(--ensemble {self.min_members} or more)")

    def check_state(self, state: PlanningState) -> None:
        """ValueError unless ``state`` holds what this planner scores with: for
        planners with an ensemble, the ensemble and the candidates' rays (the
        caller makes the state); UserError for an ensemble too small for it."""
        if not self.needs_ensemble:
            return
        missing = [name for name in ("ensemble", "candidate_rays") if getattr(state, name) is None]
        if missing:
            raise ValueError(f"the {self.name} planner scores candidates with an ensemble over their rays; "
                             f"the PlanningState has no {' and no '.join(missing)}")
        rays, c = state.candidate_rays, len(state.candidates)
        if not _are_candidate_rays(rays, c):
            got = ([getattr(a, "shape", type(a).__name__) for a in rays] if isinstance(rays, (tuple, list))
                   else type(rays).__name__)
            raise ValueError(f"the {self.name} planner needs candidate_rays = (origins, directions), two numpy "
                             f"arrays of shape (C, R, 3) for the C = {c} candidates, got {got}")
        self.check_ensemble_size(state.ensemble.n_members)

    def select(self, state: PlanningState, batch: int) -> tuple[list[int], np.ndarray | None]:
        """Return ``batch`` candidate indices and the per-candidate scores (C,) they were chosen by, or None."""
        raise NotImplementedError

    def checked_select(self, state: PlanningState, batch: int) -> tuple[list[int], np.ndarray | None]:
        """:meth:`select`, with its answer checked (a planner of the user's own
        may answer anything): UserError unless it is ``batch`` candidate indices and
        C scores or None. Returns the picks as ints and the scores as float64.
        The planner gets its own copies of the candidate and captured lists, so
        that changing them in place changes nothing of the run's."""
        answer = self.select(replace(state, candidates=list(state.candidates), captured=list(state.captured)), batch)
        n = len(state.candidates)
        expected = (f"select(state, batch) must return (indices, scores): {batch} candidate indices (whole "
                    f"numbers) in [0, {n}), and {n} scores or None")
        if not (isinstance(answer, tuple) and len(answer) == 2):
            raise UserError(f"the {self.name} planner answered {type(answer).__name__}: {expected}")
        picks, scores = answer
        try:
            indices = list(np.asarray(picks).reshape(-1))
            scores = None if scores is None else np.asarray(scores, dtype=np.float64)
        except (TypeError, ValueError):
            raise UserError(f"the {self.name} planner answered ({_one_line(picks)}, {_one_line(scores)}): "
                            f"{expected}") from None
        if len(indices) != batch or not all(is_whole(i) and 0 <= i < n for i in indices):
            raise UserError(f"the {self.name} planner picked {_one_line(picks)}: {expected}")
        if scores is not None and scores.shape != (n,):
            raise UserError(f"the {self.name} planner gave scores of shape {scores.shape}: {expected}")
        return [int(i) for i in indices], scores

    def options(self) -> dict:
        """The planner's settings, recorded in run.json."""
        return {}


def unseen(state: PlanningState) -> np.ndarray:
    """Boolean mask (C,) of candidates not captured yet and within reach."""
    mask = np.ones(len(state.candidates), dtype=bool)
    mask[list(state.captured)] = False
    mask[list(state.out_of_reach)] = False
    return mask


def check_batch(allowed: np.ndarray, batch: int) -> None:
    """UserError when fewer than ``batch`` candidates are ``allowed`` (C,) bool."""
    n_left = int(np.count_nonzero(allowed))
    if n_left < batch:
        raise UserError(f"only {n_left} candidate views are left to choose from, asked for {batch}")


def greedy_top(scores: np.ndarray, allowed: np.ndarray, batch: int) -> list[int]:
    """Indices of the ``batch`` best allowed scores, best first (ties: lower index).

    A NaN score (a candidate the model could not score) is never picked; +inf
    ranks first.
    """
    scores, allowed = np.asarray(scores, dtype=np.float64), np.asarray(allowed, dtype=bool)
    if scores.ndim != 1 or scores.shape != allowed.shape:
        raise ValueError(f"greedy_top: scores and allowed must both be (C,) arrays, one entry per candidate; "
                         f"got shapes {scores.shape} and {allowed.shape}")
    check_batch(allowed, batch)
    ok = np.flatnonzero(allowed & ~np.isnan(scores))
    if len(ok) < batch:
        n_left = int(np.count_nonzero(allowed))
        raise UserError(f"only {len(ok)} candidate views are left to choose from, asked for {batch} "
                        f"({n_left - len(ok)} of the {n_left} left could not be scored)")
    order = np.lexsort((ok, -scores[ok]))
    return [int(ok[i]) for i in order[:batch]]


REGISTRY: dict[str, type] = {}


def _origin(cls) -> tuple:
    """Where a class is defined: its module's file (or, without one, the
    module's name) and its qualified name. One file imported as a module and
    loaded as ``FILE.py:CLASS`` gives two modules of the same classes."""
    file = getattr(sys.modules.get(cls.__module__), "__file__", None)
    return (str(Path(file).resolve()) if file else cls.__module__, cls.__qualname__)


def register(cls):
    """Class decorator: make a planner available by its ``name`` (in this process)."""
    if not isinstance(cls.name, str) or not cls.name or ":" in cls.name:
        raise UserError(f"a registered planner's name is a word without ':', got {cls.name!r}")
    if cls.name == Planner.name:
        raise UserError(f"give {cls.__name__} a name to be registered by (a class attribute: name = \"...\")")
    # Names are looked up in any case: one that differs only in case would be ambiguous.
    twin = next((k for k in REGISTRY if k.casefold() == cls.name.casefold() and k != cls.name), None)
    if twin is not None:
        raise UserError(f"'{cls.name}' differs from the name of the planner {REGISTRY[twin].__qualname__} "
                        f"('{twin}') only in case; give {cls.__name__} another name")
    taken = REGISTRY.get(cls.name)
    if taken is not None and taken.__module__.startswith(__name__.rpartition(".")[0] + ".") and taken is not cls:
        raise UserError(f"'{cls.name}' is the name of one of mitsuba-active's planners; "
                        f"give {cls.__name__} another name")
    # The same class defined again (its module reloaded, or its file loaded as FILE.py:CLASS
    # after an import of it) takes its name back; another class does not.
    if taken is not None and _origin(taken) != _origin(cls):
        raise UserError(f"'{cls.name}' is the name of the planner {taken.__module__}.{taken.__qualname__} "
                        f"already; give {cls.__name__} another name")
    REGISTRY[cls.name] = cls
    return cls


def _parse(name: str) -> tuple[str | None, str]:
    """``(where, class name)`` of a reference: ``where`` is a ``.py`` path or a
    dotted module; ``(None, name)`` for a registered name."""
    where, sep, cls = name.rpartition(":")
    return (where, cls) if sep else (None, name)


def _is_file(where: str | None) -> bool:
    return where is not None and where.endswith(".py")


def registered_name(name):
    """A registered planner's name as it was registered, given in any case
    (``RFE`` is ``rfe``); any other name as it is."""
    return name if not isinstance(name, str) or ":" in name else choice_named(name, REGISTRY)


def resolve_reference(name: str, folder=".") -> str:
    """A planner name with the file of a ``FILE.py:CLASS`` reference made
    absolute (relative to ``folder``), so that it names the same file from
    anywhere; registered names as registered (:func:`registered_name`), and
    ``MODULE:CLASS`` references as they are."""
    where, cls = _parse(name)
    return f"{(Path(folder) / where).resolve()}:{cls}" if _is_file(where) else registered_name(name)


def planner_label(name: str) -> str:
    """A short name of a planner for tables, plots and messages: a registered
    name as registered, ``FILE.py:CLASS`` as ``file.py:CLASS`` (without its folder)."""
    where, cls = _parse(name)
    return f"{Path(where).name}:{cls}" if _is_file(where) else registered_name(name)


def planner_folder(name: str) -> str:
    """The part of a run folder's name that names its planner."""
    return folder_name(planner_label(name))


def is_planner_file(name) -> bool:
    """Whether ``name`` is a ``FILE.py:CLASS`` reference."""
    return isinstance(name, str) and _is_file(_parse(name)[0])


#: Code of the user's own planners as loaded: absolute path of a planner file,
#: or a module's name -> (module, sha256 of its file's content then).
_LOADED: dict[str, tuple] = {}


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _failure(where: str, exc: BaseException, path: str | None = None) -> UserError:
    """One line for an exception raised while loading a planner's code, with
    the line of the planner's file where it was raised."""
    if isinstance(exc, SyntaxError) and exc.filename == path:  # its str() names the file and line already
        message, line = exc.msg, exc.lineno
    else:
        frames = [f for f in traceback.extract_tb(exc.__traceback__) if f.filename == path]
        message, line = str(exc), frames[-1].lineno if frames else None
    at = f" (line {line})" if line else ""
    return UserError(f"cannot load the planner {where}: {type(exc).__name__}: {_one_line(message)}{at}")


def _load_file(path: str):
    """The module of a planner file, loaded again whenever the file has changed
    (in a long session, the code that runs is always the file's). As for a
    script, the file's folder is on ``sys.path``, so modules beside it import."""
    file = Path(path)
    if not file.is_file():
        raise UserError(not_a_file(file, "planner file"))
    digest = hashlib.sha256(file.read_bytes()).hexdigest()
    if path in _LOADED and _LOADED[path][1] == digest:
        return _LOADED[path][0]
    if str(file.parent) not in sys.path:
        sys.path.append(str(file.parent))
    name = "mitsuba_active_user_planner_" + hashlib.sha256(path.encode()).hexdigest()[:12]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses and pickling look classes up there
    try:
        spec.loader.exec_module(module)
    # The planner's own code: a bug there is named with its line. A file that
    # calls sys.exit() (a script's habit) would otherwise end the command silently.
    except (Exception, SystemExit) as exc:
        sys.modules.pop(name, None)
        raise _failure(f"file {file}", exc, path) from None
    _LOADED[path] = (module, digest)
    return module


def _load_module(name: str):
    """An importable module holding a planner (imported once, as Python does)."""
    if name in _LOADED:
        return _LOADED[name][0]
    if name.startswith(".") or not all(part.isidentifier() for part in name.split(".")):
        raise UserError(f"'{name}' is neither a planner file (FILE.py:CLASS) nor a module (MODULE:CLASS)")
    try:
        module = importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and (name == exc.name or name.startswith(exc.name + ".")):
            raise UserError(f"no module named '{name}' for a planner (a planner in a file is named "
                            f"FILE.py:CLASS)") from None
        raise _failure(f"module {name}", exc) from None
    except (Exception, SystemExit) as exc:
        raise _failure(f"module {name}", exc) from None
    path = getattr(module, "__file__", None)
    _LOADED[name] = (module, hashlib.sha256(Path(path).read_bytes()).hexdigest() if path else None)
    return module


def planner_class(name: str) -> type:
    """The :class:`Planner` subclass that a registered name or a reference names."""
    if not isinstance(name, str) or not name:
        hint = (f"; register {name.__name__} with @register and give its name" if inspect.isclass(name)
                and issubclass(name, Planner) else "")
        raise UserError(f"a planner is named by a string (a registered name or FILE.py:CLASS), got {name!r}{hint}")
    where, cls_name = _parse(name)
    if where is None:
        if registered_name(name) not in REGISTRY:
            raise UserError(f"{unknown_choice('planner', name, sorted(REGISTRY))}, "
                            "or name a planner of your own as FILE.py:CLASS")
        return REGISTRY[registered_name(name)]
    module = _load_file(str(Path(where).resolve())) if _is_file(where) else _load_module(where)
    cls = getattr(module, cls_name, None)
    if cls is None:
        found = [k for k, v in vars(module).items()
                 if inspect.isclass(v) and issubclass(v, Planner) and v.__module__ == module.__name__]
        have = f"; it defines {', '.join(found)}" if found else "; it defines no Planner subclass"
        raise UserError(f"{where} has no class '{cls_name}'{have}")
    if not (inspect.isclass(cls) and issubclass(cls, Planner)):
        raise UserError(f"{name} is not a planner: a planner is a subclass of mitsuba_active.planners.Planner")
    if cls.select is Planner.select:  # found now, not after the ground truth and the first training
        raise UserError(f"{planner_label(name)} has no select(state, batch) method")
    return cls


def planner_digest(name: str) -> str | None:
    """SHA-256 of the file a planner of the user's own comes from, as its code
    was loaded (only that file: not the modules it imports); None for the
    package's planners. Recorded in run.json: a run is not resumed, nor
    counted in a suite, with other code (one that stopped before its planner
    chose a view starts over, see :func:`~mitsuba_active.run.other_planner_code`)."""
    where = _parse(name)[0] if isinstance(name, str) else None
    if where is None:
        return None
    planner_class(name)  # loads the code (a file again, if it changed)
    return _LOADED[str(Path(where).resolve()) if _is_file(where) else where][1]


def make_planner(name: str, /, **options) -> Planner:
    """Instantiate a planner by registered name or reference; unknown names and options raise UserError."""
    cls = planner_class(name)
    try:
        planner = cls(**options)
    except (TypeError, ValueError) as exc:
        # object.__init__'s (*args, **kwargs) is no option: a planner without __init__ takes none.
        params = [] if cls.__init__ is object.__init__ else inspect.signature(cls.__init__).parameters.values()
        if any(q.kind == q.VAR_KEYWORD for q in params):
            unknown, known = set(), ""
        else:
            accepted = [q.name for q in params if q.name != "self" and q.kind in (q.POSITIONAL_OR_KEYWORD,
                                                                                 q.KEYWORD_ONLY)]
            unknown = set(options) - set(accepted)
            known = f" (it takes {', '.join(accepted)})" if accepted else " (it takes none)"
        why = f"unknown option {', '.join(sorted(unknown))}" if unknown else _one_line(exc)
        raise UserError(f"bad option for planner '{planner_label(name)}': {why}{known}") from None
    if cls.name == Planner.name:  # messages name the planner ("the ... planner needs ...")
        planner.name = planner_label(name)
    return planner
