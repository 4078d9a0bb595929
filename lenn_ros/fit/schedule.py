"""What ``fit`` runs side by side on the cores: several outputs' views, and the refinement of the best candidates.

The views of a several-output fit are queued as a core frees, each waiting only for what it
needs (:class:`ViewQueue`); the refinement's blocks of every output's best candidates run
in one pool, and only the candidate that then leads is refined on all its samples
(:func:`refine_outputs`). Apart from the procedure: how the work is laid on the cores
changes no model (each job is a pure function of what it is given, done ahead or not).
"""

from __future__ import annotations

import functools
from typing import Any

from lenn_ros.core.threads import cores, side_by_side
from lenn_ros.fit.refinement import Refinement, blocks_choice, fold_history, refine_on_folds
from lenn_ros.fit.result import OutputFit
from lenn_ros.fit.selection import Candidate, order_candidates

#: candidates (best first) whose weights are refined on simulation error; the best refined one is kept
REFINED_CANDIDATES = 3


def views_side_by_side(
    n_y: int, view: Any, together: Any, say: Any, spare: Any = None
) -> tuple[dict[str, list[OutputFit]], dict[str, tuple[float, list[float]]], dict[Any, Any]]:
    """Every output's two views on the machine's cores, each kind's joint score
    (:func:`~lenn_ros.fit.selection.joint_block_score`), and what was done ahead of the choice between them
    (``spare``: see :class:`ViewQueue`).

    An output's view with the others' past is offered the structures that served it alone, so
    it waits for its own view. The twelve views of a six-joint robot are queued one by one as
    a core frees (:class:`ViewQueue`); six pairs as tasks left a core idle at the end for the
    length of one output's two views. What each output says is printed in order, as soon as
    both its views are done.
    """
    from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait

    queue, workers = ViewQueue(n_y, view, together, spare), cores()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: dict[Any, tuple[str, Any]] = {}
        while True:
            while len(pending) < workers and (task := queue.next_task()) is not None:
                pending[pool.submit(*task[0])] = task[1]
            if not pending:
                break
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                queue.finished(pending.pop(future), future.result())
            queue.tell(say)
    return queue.fits, queue.scores, queue.ahead


class ViewQueue:
    """What :func:`views_side_by_side` starts next: an output's second view as soon as its first is done,
    else the next output's first, and each kind's joint score as soon as all its views are in (the own
    views' beside the remaining views, not after them). On one core: the outputs in order, both views each.

    ``spare(own fits)``: (key, call) jobs worth doing before the choice between the kinds is known,
    started only when a core would otherwise wait (the last views and the coupled views' joint score
    leave one idle), never after both scores are in; their results are ``ahead``, by key. ``fit`` gives
    the own views' refinement blocks (:func:`refinement_jobs`): the own views are the ones used
    unless reading the other outputs wins, and refining them waited for that choice on one core.
    """

    def __init__(self, n_y: int, view: Any, together: Any, spare: Any = None) -> None:
        self.n_y, self.view, self.together, self.spare = n_y, view, together, spare
        self.said: list[list[str]] = [[] for _ in range(n_y)]
        self.fits: dict[str, list[Any]] = {"own": [None] * n_y, "coupled": [None] * n_y}
        self.scores: dict[str, tuple[float, list[float]]] = {}
        self.ready: list[int] = []  # outputs whose own view is done and whose other view has not started
        self.started = self.told = 0
        self.scoring: set[str] = set()  # the kinds whose joint score has started
        self.spare_jobs: list[tuple[Any, Any]] | None = None  # made once the own views are all in
        self.ahead: dict[Any, Any] = {}

    def _score_task(self, kind: str) -> tuple[tuple, tuple[str, Any]] | None:
        if kind in self.scoring or any(f is None for f in self.fits[kind]):
            return None
        self.scoring.add(kind)
        return (self.together, self.fits[kind]), ("score", kind)

    def next_task(self) -> tuple[tuple, tuple[str, Any]] | None:
        """(the call, its tag) of the next task that can start, or None."""
        if (task := self._score_task("own")) is not None:
            return task
        if self.ready:
            j = self.ready.pop(0)
            return (self.view, j, "coupled", self.fits["own"][j], self.said[j]), ("coupled", j)
        if self.started < self.n_y:
            j = self.started
            self.started += 1
            return (self.view, j, "own", None, self.said[j]), ("own", j)
        if (task := self._score_task("coupled")) is not None:
            return task
        if self.spare is None or "own" not in self.scoring or len(self.scores) == 2:
            return None
        if self.spare_jobs is None:
            self.spare_jobs = list(self.spare(self.fits["own"]))
        if not self.spare_jobs:
            return None
        key, call = self.spare_jobs.pop(0)
        return (call,), ("ahead", key)

    def finished(self, tag: tuple[str, Any], result: Any) -> None:
        kind, j = tag
        if kind == "score":
            self.scores[j] = result
        elif kind == "ahead":
            self.ahead[j] = result
        else:
            self.fits[kind][j] = result
            if kind == "own":
                self.ready.append(j)

    def tell(self, say: Any) -> None:
        """Print what the outputs whose views are all done said, in order."""
        while self.told < self.n_y and self.fits["coupled"][self.told] is not None:
            for line in self.said[self.told]:
                say(line)
            self.told += 1


def refinement_jobs(fits: list[OutputFit]) -> list[tuple[tuple[int, int], Any]]:
    """((candidate id, block), call) of every :func:`~lenn_ros.fit.refinement.fold_history` that
    :func:`refine_outputs` needs for these outputs, in its order: each a pure function of the candidate's
    fold weights and the record, so done ahead (:class:`ViewQueue`) it is what it would be done then."""
    return [
        ((id(candidate), fold), functools.partial(fold_history, candidate, fitted.record, fold))
        for fitted in fits
        for candidate in refinement_targets(fitted.candidates)
        for fold in range(len(candidate.fold_weights))
    ]


def refine_outputs(fits: list[OutputFit], say: Any, workers: int, ahead: dict | None = None) -> None:
    """Refine each output's :func:`refinement_targets` on simulation error (iterations chosen on the blocks),
    then choose again among them and the input-only ones (:func:`after_refinement`).

    Refinement can reorder candidates (a hinge model that least squares left behind may
    simulate best once refined), so every target's blocks are refined, side by side in one
    pool of ``workers`` threads (a candidate's blocks are independent: three candidates on two
    cores by candidate left one idle for a third of Bouc-Wen's refinement). The blocks' pooled
    error after the count they choose is each target's score. Only the candidate that then
    leads is refined on all its samples (:func:`~lenn_ros.fit.refinement.refine_on_folds`);
    if its soundness check undoes iterations, its score rises and the choice is made again,
    until the leader is one refined on all samples. The others keep their least-squares
    weights and the blocks' figure, reported as not applied: refining all samples of a model
    that is not used cost Bouc-Wen 3 s. ``ahead``: blocks' histories already done, by
    :func:`refinement_jobs`' key.
    """
    targets = [(fitted, candidate) for fitted in fits for candidate in refinement_targets(fitted.candidates)]
    for fitted, candidate in targets:
        named = f"output {fitted.name}: " if len(fits) > 1 else ""
        say(f"{named}refining {candidate.spec.label} ({candidate.terms} terms) on simulation error")
    ahead = ahead or {}
    jobs = refinement_jobs(fits)
    left = [job for job in jobs if job[0] not in ahead]
    computed = side_by_side(lambda job: job[1](), left, workers)
    done = {**ahead, **{key: history for (key, _), history in zip(left, computed, strict=True)}}
    history_of: dict[int, list] = {id(candidate): [] for _, candidate in targets}
    for key, _ in jobs:  # each candidate's blocks in order
        history_of[key[0]].append(done[key])
    for _fitted, candidate in targets:
        _score_refinement(candidate, blocks_choice(history_of[id(candidate)]))
    while leaders := [
        (fitted, leader)
        for fitted in fits
        for leader in contenders(fitted, targets)[:1]
        if not (leader.refinement or {}).get("applied", True)
    ]:
        results = side_by_side(
            lambda pair: refine_on_folds(pair[1], pair[0].record, history_of[id(pair[1])]), leaders, workers
        )
        for (_fitted, candidate), result in zip(leaders, results, strict=True):
            _score_refinement(candidate, result)
    for fitted in fits:
        fitted.chosen, fitted.refinement = after_refinement(fitted.candidates, contenders(fitted, targets))


def _score_refinement(candidate: Candidate, result: Refinement) -> None:
    """Record what the refinement did (or what the blocks chose) as the candidate's score."""
    candidate.refinement = result.as_dict()
    candidate.rmse_validation = result.rmse_blocks_after


def contenders(fitted: OutputFit, targets: list[tuple[OutputFit, Candidate]]) -> list[Candidate]:
    """An output's refined and input-only candidates, in the order :func:`after_refinement` would choose."""
    refined = [candidate for owner, candidate in targets if owner is fitted]
    input_only = [c for c in fitted.candidates if c.model is not None and c.spec.registered.input_only]
    return order_candidates(refined + input_only)


def refinement_targets(candidates: list[Candidate]) -> list[Candidate]:
    """The candidates refined on simulation error: the first REFINED_CANDIDATES usable ones that feed back
    their output (an input-only ``fir`` one's least squares already minimise its free-run error)."""
    return [c for c in candidates if c.model is not None and not c.spec.registered.input_only][:REFINED_CANDIDATES]


def after_refinement(candidates: list[Candidate], contenders: list[Candidate]) -> tuple[Candidate, dict[str, Any]]:
    """Choose again among the refined candidates and the input-only ones (``contenders``, as :func:`contenders`
    orders them); the report's list puts them first, the chosen one leading. An input-only model
    (``fir``) is never refined, nor does it take a refinement's place: its least squares already
    minimise its simulation error (its free run is its one-step prediction)."""
    for candidate in contenders:
        candidates.remove(candidate)
    candidates[:0] = contenders
    chosen = candidates[0]
    return chosen, {"done": True, **(chosen.refinement or {"iterations": 0, "tried": 0, "input_only": True})}
