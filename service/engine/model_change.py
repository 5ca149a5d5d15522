"""Replacing a well's model while it keeps learning (``PUT /wells/{well}/model``).

Four steps, the first and last on the well's worker between two messages, so no sample
goes unanswered and no measurement is skipped:

1. *snapshot*: the worker hands out a copy of the well's learner and starts noting what
   the current model learns from now on (``WellState.catch_up``);
2. *refit* (on a thread of its own, off the worker): the copy fits the new model on
   everything the well remembers and compares it with the current one on the latest
   fifth (:meth:`vfm_core.learning.streaming.WellLearner.refit_as`); the caller waits at most
   ``model.change_budget_s``, after which the change is abandoned (503) and the current
   model kept; at most ``http.max_model_changes`` fits run at once (503 beyond);
3. *catch-up*: the worker teaches the new model what arrived during the fit;
4. *swap*: the worker commits what its batch holds, then the new model's checkpoint, and
   only then swaps it in with a higher version; the rolling error restarts with it.

A failed or abandoned fit sends a *cancel* step instead. When the held-out check says the
new model is worse (its MAPE above the current one's), the change is refused
(:class:`~service.errors.Conflict`, 409, both MAPEs in the sentence) unless the request
confirms it (``confirm_worse``).

After the swap the replaced model runs on as the *shadow* of a trial
(:mod:`service.engine.trial`) that keeps the change or rolls it back; the replaced model
is also kept in the store as an earlier version (``model_versions``, the latest
``trial.keep_versions``), and :meth:`ModelChanges.rollback` (``POST
/wells/{well}/model/rollback``) brings any kept version back: its checkpoint re-learns,
off the worker, every measurement the well learned since it was replaced (in learning
order, from the store), then catches up and is swapped in as a change is, with a higher
version; a rollback starts no trial. :func:`install` is the swap both share with a
trial's own rollback (:func:`service.engine.trial.install`). A change to or from a
field-wide model (``mtl``) is refused (:class:`~service.errors.InvalidRequest`): its
network is shared by every well, so it is chosen for all of them in the config. The method is checked by the
same rule as the config (:func:`service.config.method_problem`: a registered method the
streaming learner runs, with a retrain period of at least ``model.min_retrain_period_s``).
Refusals are domain errors: :class:`~service.errors.UnknownWell`,
:class:`~service.errors.NotAllowed` (an effect from a module not in
``model.effect_modules``), :class:`~service.errors.InvalidRequest` (an unknown model,
effect or method), :class:`~service.errors.Conflict` (a change of the well is already
running), :class:`~service.errors.Busy` and :class:`~service.errors.Stopping`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from typing import Any

from service.config import Settings, method_problem
from service.engine.checkpoints import Checkpoints, configured_spec
from service.engine.fairqueue import FairQueue
from service.engine.items import Batch, ModelStep
from service.engine.learners import Learner, apply_budget, fit_budget
from service.engine.state import WellState
from service.engine.trial import Trial, install
from service.errors import Busy, Conflict, InvalidRequest, NotAllowed, Stopping, unknown_well
from service.store import Op, Store
from vfm_core.errors import VFMError
from vfm_core.jobs.diagnose_results import MATERIAL_MAPE_NEAR_FLOOR
from vfm_core.learning.streaming import WellLearner
from vfm_core.models import MODELS
from vfm_core.timeutil import from_ns

__all__ = ["ModelChanges", "check_effect_modules", "effect_module"]

logger = logging.getLogger("vfm.service.engine")


def effect_module(text: str) -> str | None:
    """The module an effect spec names (``mypkg.effects:Scale[:k=v]``), None for a library effect."""
    base = text.split("=", 1)[0].rsplit(":", 1)[0] if "=" in text else text
    return base.split(":", 1)[0] if ":" in base else None


def check_effect_modules(texts: Sequence[str], allowed: Sequence[str], what: str) -> None:
    """NotAllowed for an effect spec (``what``: "effect", "candidate", ...) that names a
    module outside ``allowed`` (``model.effect_modules``): over HTTP only the library's
    effects and classes from those modules are imported."""
    for text in texts:
        module = effect_module(text)
        if module is not None and module not in allowed:
            raise NotAllowed(
                f"The {what} '{text}' names the module '{module}', which is not in "
                "model.effect_modules; over HTTP only the library's effects and classes from "
                "those modules can be used."
            )


class ModelChanges:
    """Model changes of the wells: the request on the caller's thread, the steps on the worker."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        wells: Mapping[str, WellState],
        queues: list[FairQueue],
        checkpoints: Checkpoints,
        stopping: threading.Event,
        catch_up: Callable[[WellLearner, int], bool] | None = None,
    ) -> None:
        self.settings = settings
        self.store = store
        self.wells = wells
        self.queues = queues
        self.checkpoints = checkpoints
        self.stopping = stopping
        self.catch_up = catch_up
        self._changing: set[str] = set()
        self._lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(settings.http.max_model_changes)
        self._fits: set[threading.Thread] = set()

    def wait(self, timeout: float) -> bool:
        """Wait for the fits still running (at a stop); True when none is left."""
        deadline = time.monotonic() + timeout
        for thread in list(self._fits):
            thread.join(max(0.0, deadline - time.monotonic()))
        return not any(t.is_alive() for t in self._fits)

    @staticmethod
    def _field_wide_problem(well: str, learner: Learner, model: str | None) -> str | None:
        """Why a change to or from a field-wide model (``mtl``) cannot be made for one well,
        as a sentence; None when the change is per well. Its network is shared by every well
        of the field and learns from them in time order: one well cannot leave or join it
        alone without changing the others' predictions."""
        if learner.shares_model:
            return (
                f"Well {well} is served by the field-wide model {learner.name}, whose network is "
                "shared with every other well of this service; its model cannot be changed for "
                "one well. Set model.name in the config (it applies to every well) and restart."
            )
        if model is not None and model in MODELS and MODELS[model].shared:
            return (
                f"The model '{model}' is field-wide: one network shared by every well, learning "
                "from them in time order; it cannot be chosen for one well. Set model.name = "
                f"'{model}' in the config (it applies to every well) and restart."
            )
        return None

    # -- the caller's side (an HTTP thread) -----------------------------------------------
    def change(
        self,
        well: str,
        model: str | None = None,
        effects: list[str] | None = None,
        method: str | None = None,
        confirm_worse: bool = False,
    ) -> dict[str, Any]:
        """Replace a well's model: fit the new one on the well's stored history, then swap.

        Returns the change (models and versions before and after, held-out MAPE, what was
        caught up, the trial started), checkpointed before this returns. Effects given as
        ``module:Class`` must come from a module listed in ``model.effect_modules``. When
        the held-out check says the new model is worse, the change is refused
        (:class:`~service.errors.Conflict`) unless ``confirm_worse``.
        """
        st = self.wells.get(well)
        if st is None:
            raise unknown_well(well)
        field_problem = self._field_wide_problem(well, st.learner, model)
        if field_problem is not None:
            raise InvalidRequest(field_problem)
        effects = list(effects or [])
        check_effect_modules(effects, self.settings.model.effect_modules, "effect")
        old = st.learner
        model = model or old.model_name
        problem = method_problem(
            method or old.method.text, self.settings.model.min_retrain_period_s
        )
        if problem is not None:
            raise InvalidRequest(problem)
        try:  # check the request before any work: a typo fails at once
            WellLearner(well, model, method or old.method.text, effects=effects)
        except VFMError as exc:
            raise InvalidRequest(str(exc)) from None
        fit = self._begin(well)
        try:
            copy: WellLearner = self._step(st, "snapshot")
            logger.info(
                "Model change of %s: fitting %s%s (%s) on %d stored measurement(s).",
                well,
                model,
                "".join(f"+{e}" for e in effects),
                method or old.method.text,
                copy.remembered,
            )
            started = time.perf_counter()
            try:
                new, scores = fit.run(
                    lambda: copy.refit_as(
                        model, effects, method, time_budget_s=fit_budget(self.settings.model)
                    )
                )
            except BaseException as exc:
                self._step(st, "cancel")
                if isinstance(exc, VFMError):
                    raise InvalidRequest(str(exc)) from None
                raise
            apply_budget(new, self.settings.model)
            scores["fit_s"] = round(time.perf_counter() - started, 2)
            worse = _worse(scores)
            if worse and not confirm_worse:
                self._step(st, "cancel")
                # a change of the method alone keeps the model's name: name the methods then
                named = new.method.text != old.method.text
                after = f"{new.name} ({new.method.text})" if named else new.name
                now = f"{old.name} ({old.method.text})" if named else old.name
                raise Conflict(
                    f"The held-out check says {after} is worse than {now} for {well}: "
                    f"MAPE {scores['before']:.2f} % now against {scores['after']:.2f} % with "
                    f"the change, each fitted on the older stored measurements and learning "
                    f"with its method over the latest {scores.get('holdout_rows')}. Nothing "
                    "was changed; send the request again with "
                    '"confirm_worse": true to apply it anyway (its trial will compare both).'
                )
            scores["confirmed_worse"] = bool(worse)
            change: dict[str, Any] = self._step(st, "swap", new, scores)
            return change
        finally:
            fit.release()

    def _step(
        self,
        st: WellState,
        kind: str,
        learner: WellLearner | None = None,
        scores: dict[str, Any] | None = None,
    ) -> Any:
        """Run one step of a model change on the well's worker and wait for it.

        The snapshot waits at most 5 s for queue room (busy); a swap or cancel waits for
        room as long as it takes, since it must not be dropped once the copy is out.
        """
        if self.stopping.is_set():
            raise Stopping("The service is stopping; retry after it restarts.")
        fut: Future[Any] = Future()
        item = ModelStep(st.well, kind, fut, learner, scores or {})
        snapshot = kind == "snapshot"
        full = self.queues[st.worker].put(
            st.well, item, timeout=5.0 if snapshot else None, force=not snapshot
        )
        if full != "ok":
            raise Busy("The service is busy (its queue is full); retry in a few seconds.")
        return fut.result()

    # -- the worker's side --------------------------------------------------------------------
    def on_step(self, item: ModelStep, b: Batch, flush: Callable[[Batch], None]) -> None:
        """Run a step on the well's worker; ``flush`` commits what the batch holds so far."""
        st = self.wells.get(item.well)
        if st is None:  # retired meanwhile
            item.future.set_exception(unknown_well(item.well))
            return
        if item.kind == "snapshot":
            copy = WellLearner.restore(st.learner.checkpoint())
            st.catch_up = []
            item.future.set_result(copy)
            return
        if item.kind == "cancel":
            st.catch_up = None
            item.future.set_result(None)
            return
        if item.kind == "mark":  # a rollback: what the store holds up to now is committed
            flush(b)
            b.clear()
            st.catch_up = []
            item.future.set_result(st.learn_seq)
            return
        self._swap(st, item, b, flush)

    def _swap(
        self, st: WellState, item: ModelStep, b: Batch, flush: Callable[[Batch], None]
    ) -> None:
        new, old = item.learner, st.learner
        assert new is not None
        scores = dict(item.scores)
        kind = str(scores.pop("_kind", "change"))
        # the method named when it changed: a change of the method alone keeps the name
        how = f" ({new.method.text})" if new.method.text != old.method.text else ""
        note = str(scores.pop("_note", "") or f"replaced by {new.name}{how} over HTTP")
        extra = scores.pop("_extra", None)
        caught_up = self._catch_up(st, new)
        # commit what the batch holds so far, then the new model's checkpoint on its own:
        # the swap happens only once that checkpoint is in the store
        flush(b)
        b.clear()
        saved = (
            st.checkpoint_version,
            list(st.model_changes),
            list(st.trials),
            list(st.errors),
        )
        running = st.trial
        when = st.last_time_ns
        ops: list[Op] = []
        shadow = running.shadow if running is not None else None
        if running is not None:
            running.supersede(
                st, ops, when, f"The model was replaced ({kind}) by {new.name} while it ran."
            )
        new.renumber(old.version + 1)
        trial = self._start_trial(st, new, old, when) if kind == "change" else None
        try:
            change = install(
                st,
                new,
                self.checkpoints,
                ops,
                when,
                kind=kind,
                note=note,
                keep_versions=self.settings.trial.keep_versions,
                config=configured_spec(self.settings),
                holdout=scores,
                caught_up=len(caught_up),
                extra=extra,
            )
            self.store.write(ops)
        except Exception:  # nothing was stored: the well goes on as before
            st.learner = old
            st.checkpoint_version = saved[0]
            st.model_changes.clear()
            st.model_changes.extend(saved[1])
            st.trial = running
            if running is not None:  # it goes on
                running.outcome, running.shadow, running.ended_ns = "running", shadow, None
            st.trials.clear()
            st.trials.extend(saved[2])
            st.params_version = None  # the next learning step records the old one again
            st.errors.clear()
            st.errors.extend(saved[3])
            st.refresh()
            raise
        out = dict(change)
        out["trial"] = trial.view() if trial is not None else None
        b.answer(item.future, out)

    def _catch_up(self, st: WellState, new: WellLearner) -> list[Any]:
        """The new learner learns the measurements that came while it was built (the
        well's ``catch_up``, then cleared); returns them."""
        try:
            caught_up = list(st.catch_up or [])
            for inputs, q_total, time_ns, source in caught_up:
                if self.catch_up is not None:
                    self.catch_up(new, time_ns)
                new.learn(list(inputs), q_total, from_ns(time_ns), source)
        finally:
            st.catch_up = None
        return caught_up

    def _start_trial(
        self, st: WellState, new: Learner, old: Learner, when: int | None
    ) -> Trial | None:
        """A trial of a change, with the replaced model (its own, not shared) running on as
        its shadow; None when trials are off or the old model is shared."""
        if not self.settings.trial.enabled or old.shares_model:
            return None
        trial = Trial(
            well=st.well,
            since_ns=when if when is not None else 0,
            model=new.name,
            shadow_model=old.name,
            version=new.version,
            shadow_version=old.version,
            shadow=old,
            settings=self.settings.trial,
            method=new.method.text,
            shadow_method=old.method.text,
        )
        st.trial = trial
        return trial

    def rollback(self, well: str, version: int) -> dict[str, Any]:
        """Bring back an earlier model version of a well (``POST /wells/{well}/model/rollback``).

        The kept checkpoint of ``version`` (``model_versions``) re-learns, off the worker,
        every measurement the well learned since that model was replaced, from the store
        in learning order (as it would have learned them live); then it catches up with
        what arrived meanwhile and is swapped in with a higher version. A running trial
        ends ``superseded``; a rollback starts none. Returns the change."""
        st = self.wells.get(well)
        if st is None:
            raise unknown_well(well)
        field_problem = self._field_wide_problem(well, st.learner, None)
        if field_problem is not None:
            raise InvalidRequest(field_problem)
        row = self.store.model_version(well, version)
        if row is None:
            kept = [r.version for r in self.store.model_versions(well)]
            raise InvalidRequest(
                f"Version {version} of {well} is not kept; the kept earlier versions are "
                f"{', '.join(map(str, kept)) if kept else 'none'} (the latest "
                f"trial.keep_versions = {self.settings.trial.keep_versions} are kept)."
            )
        fit = self._begin(well)
        try:
            seq: int = self._step(st, "mark")

            def relearn() -> tuple[WellLearner, int]:
                learner = WellLearner.restore(row.blob)
                n = 0
                for r in self.store.learned_after(well, row.learn_seq):
                    if r.learn_seq > seq:  # learned after the mark: taught at the swap
                        break
                    if self.catch_up is not None:
                        self.catch_up(learner, r.time_ns)
                    learner.learn(list(r.sample.inputs), r.q_total, from_ns(r.time_ns), r.source)
                    n += 1
                return learner, n

            logger.info(
                "Rollback of %s to version %d (%s, %s): re-learning what it learned since.",
                well,
                version,
                row.model,
                row.method,
            )
            try:
                learner, n = fit.run(relearn)
            except BaseException as exc:
                self._step(st, "cancel")
                if isinstance(exc, VFMError):
                    raise InvalidRequest(str(exc)) from None
                raise
            apply_budget(learner, self.settings.model)
            scores = {
                "holdout_rows": 0,
                "unit": "%",
                "_kind": "rollback",
                "_note": f"rolled back over HTTP to version {version} ({row.model}, {row.method}), "
                f"which re-learned the {n} measurement(s) learned since it was replaced",
                "_extra": {"rolled_back_to": version, "relearned": n},
            }
            change: dict[str, Any] = self._step(st, "swap", learner, scores)
            return change
        finally:
            fit.release()

    def _begin(self, well: str) -> _Fit:
        """Take the well's 'changing' mark and a fit slot (``http.max_model_changes``)."""
        if self.stopping.is_set():
            raise Stopping("The service is stopping; retry after it restarts.")
        with self._lock:
            if well in self._changing:
                raise Conflict(
                    f"A model change of {well} is already running; wait for it to finish."
                )
            if not self._slots.acquire(blocking=False):
                raise Busy(
                    f"{self.settings.http.max_model_changes} model change(s) are being fitted "
                    "(http.max_model_changes); retry when they have finished."
                )
            self._changing.add(well)
        return _Fit(self, well)


#: the least rise of the held-out MAPE (points) that makes the check say "worse": the
#: diagnosis's least change worth acting on (vfm_core.jobs.diagnose_results). Replayed with
#: each method, a harmless change moves the held-out MAPE by a few hundredths either way
#: (-0.03 to +0.04 points, 16 changes on 8 clean fields, benchmarks/bench_trials.py, s54):
#: asked about every such move, an operator learns to confirm without reading.
WORSE_BY = MATERIAL_MAPE_NEAR_FLOOR


def _worse(scores: Mapping[str, Any]) -> bool:
    """The held-out check says the new model is worse: its MAPE above the current one's by
    :data:`WORSE_BY` points or more, as the reply shows them (%, two decimals)."""
    before, after = scores.get("before"), scores.get("after")
    if before is None or after is None:
        return False
    return round(after, 2) - round(before, 2) >= WORSE_BY - 1e-9


class _Fit:
    """One model change's fit on a thread of its own, waited for at most
    ``model.change_budget_s``; its slot (``http.max_model_changes``) and the well's
    'changing' mark are released when both the caller and the fit are done."""

    def __init__(self, owner: ModelChanges, well: str) -> None:
        self.owner = owner
        self.well = well
        self._holders = 1  # the caller; the thread adds itself
        self._lock = threading.Lock()

    def run(self, work: Callable[[], Any]) -> Any:
        result: dict[str, Any] = {}
        done = threading.Event()

        def target() -> None:
            try:
                result["value"] = work()
            except BaseException as exc:  # handed to the caller
                result["error"] = exc
            finally:
                done.set()
                self.owner._fits.discard(threading.current_thread())
                self.release()

        with self._lock:
            self._holders += 1
        thread = threading.Thread(target=target, name=f"vfm-refit-{self.well}", daemon=True)
        self.owner._fits.add(thread)
        thread.start()
        budget = self.owner.settings.model.change_budget_s
        if not done.wait(budget):
            logger.warning(
                "The model change of %s did not finish its fit within %g s "
                "(model.change_budget_s); it was abandoned and the current model kept.",
                self.well,
                budget,
            )
            raise Busy(
                f"The new model of {self.well} was not fitted within {budget:g} s "
                "(model.change_budget_s); the change was abandoned and the current model kept. "
                "Fit on less data (a method with a window) or raise the budget."
            )
        if "error" in result:
            raise result["error"]
        return result["value"]

    def release(self) -> None:
        with self._lock:
            self._holders -= 1
            last = self._holders == 0
        if last:
            owner = self.owner
            with owner._lock:
                owner._changing.discard(self.well)
            owner._slots.release()
