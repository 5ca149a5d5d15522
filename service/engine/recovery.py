"""Start-up: every known well restored from its checkpoint or fitted on the history, then caught up.

The wells are those of the config (``inputs.wells``), of the store and of the history
file that this instance owns (``zenoh.wells``, see :mod:`service.scaleout`), but not those retired over HTTP (``DELETE /wells/{well}``; purge one to reuse its
id). For each well:

1. its latest checkpoint is restored if it holds the configured model (or one chosen over
   HTTP since the config last changed; :func:`service.engine.checkpoints.usable`);
2. otherwise a new learner is built, and all such wells with rows in the history file
   (before ``model.history_until``) are fitted in one batched fit
   (:func:`service.engine.learners.fit_history`), whose latest inputs become the drift reference;
3. the measurements learned after the checkpoint (all of them for a new learner) are
   re-learned from the store, in the same order, which gives back the same model bit for
   bit; the rolling error is refilled from the store;
4. the recent samples (for pairing) and the measurements still pending are loaded.

A field-wide model (``mtl``) is one :class:`vfm_core.learning.field.FieldLearner` for all
the wells: its latest snapshot (the newest usable checkpoint row of any of its wells: each
holds the whole field) is restored, and each well then re-learns what it learned after
that snapshot (the snapshot says how many of each well's measurements it holds), all
wells merged in time order, as they were learned live, so that the day rounds and the
numbers come back the same. Without a snapshot the whole field is fitted on the history
at once. A well the snapshot does not know is added at its prior (its history rows, if
any, are remembered for the next retrain but not fitted: fitting the field again would
discard what it learned).

What this changes (new wells, checkpoints of refitted models) is written in one commit.
"""

from __future__ import annotations

import heapq
import json
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import replace

import pandas as pd

from service.config import ModelSettings, Settings
from service.engine.checkpoints import Checkpoints, configured_spec, usable
from service.engine.learners import (
    Learner,
    apply_budget,
    fit_history,
    load_history,
    new_field,
    new_learner,
    train_settings,
)
from service.engine.learning import Learning
from service.engine.pools import coupled
from service.engine.state import RECENT_SAMPLES, Pending, WellState
from service.scaleout import WellSet
from service.store import AddWell, CheckpointRow, LearnedRow, Op, Store
from vfm_core.data import target_mask
from vfm_core.errors import VFMError
from vfm_core.learning.field import FieldLearner
from vfm_core.learning.streaming import WellLearner
from vfm_core.schema import INPUT_COLUMNS, SOURCE, TARGET, TIME, WELL, WELL_TEST
from vfm_core.timeutil import to_ns

__all__ = ["Recovery"]

logger = logging.getLogger("vfm.service.engine")


class Recovery:
    """Builds the wells' state on start; see the module docstring."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        learning: Learning,
        checkpoints: Checkpoints,
        worker_of: Callable[[str], int],
    ) -> None:
        self.settings = settings
        self.store = store
        self.learning = learning
        self.checkpoints = checkpoints
        self.worker_of = worker_of
        #: the field-wide model restored from a snapshot (it is not fitted on the history)
        self._field_restored: FieldLearner | None = None

    def load(self, retired: set[str] | None = None) -> dict[str, WellState]:
        """Every known well (but the ``retired``), restored or fitted and caught up, in a
        stable order."""
        cfg = self.settings
        history = load_history(cfg.model) if cfg.model.history is not None else None
        names = self._wells_to_load(history, retired or set())
        field_wide = cfg.model.field_wide
        if field_wide:
            learners, checkpoints = self._restore_field(names)
        else:
            learners, checkpoints = self._restore(names)
        fresh = [w for w in names if w not in checkpoints]
        fitted: list[str] = []
        if field_wide and self._field_restored is not None and history is not None and fresh:
            self._remember_history(self._field_restored, fresh, history)
        elif history is not None and fresh:
            fitted = _fit_fresh(learners, fresh, history, cfg.model)
        ops: list[Op] = []
        wells = self._well_states(names, learners, checkpoints, fitted, history, ops)
        # a field-wide model re-learns its wells' measurements merged in time order, and so
        # do wells whose filters share a calibration pool (cal_pool: each reads the others'
        # errors as they were before its time)
        merged = field_wide or any(coupled(st.learner) for st in wells.values())
        counts = self._relearn_all(list(wells.values()), ops, merged=merged)
        restored = relearned_total = 0
        for well, st in wells.items():
            row = checkpoints.get(well)
            relearned = counts[well]
            st.seed_rates()
            if well in fitted or (row is None and relearned):
                ops.extend(self.checkpoints.once(st))
            self._load_recent(st)
            st.refresh()
            last = st.learner.last_update
            if well in fitted and last is not None:  # the parameter history starts at the fit
                ops.extend(self.checkpoints.parameters.ops(st, to_ns(last)))
            restored += row is not None
            relearned_total += relearned
        self.store.write(ops)
        logger.info(
            "%d well(s): %d restored from checkpoints, %d fitted on the history; %d measurement(s) "
            "re-learned after the checkpoints.",
            len(names),
            restored,
            len(fitted),
            relearned_total,
        )
        return wells

    def _wells_to_load(self, history: pd.DataFrame | None, retired: set[str]) -> list[str]:
        """The wells of the configuration, the store and the history, in that order, less
        those outside this instance's wells and the retired ones (each group logged)."""
        cfg = self.settings
        in_history = [] if history is None or history.empty else history["well"].astype(str)
        names = list(dict.fromkeys([*cfg.inputs.wells, *self.store.wells(), *in_history]))
        own = WellSet(cfg.zenoh.wells)
        foreign = [w for w in names if w not in own]
        if foreign:
            logger.info(
                "%d well(s) of the store or the history are outside this instance's wells (%s) "
                "and not loaded: %s.",
                len(foreign),
                own.describe(),
                ", ".join(foreign[:10]) + (" ..." if len(foreign) > 10 else ""),
            )
            names = [w for w in names if w in own]
        skipped = [w for w in names if w in retired]
        if skipped:
            logger.info(
                "%d retired well(s) not loaded (%s); DELETE /wells/{well}?purge=true frees an id.",
                len(skipped),
                ", ".join(skipped[:10]) + (" ..." if len(skipped) > 10 else ""),
            )
            names = [w for w in names if w not in retired]
        return names

    def _well_states(
        self,
        names: list[str],
        learners: dict[str, Learner],
        checkpoints: dict[str, CheckpointRow],
        fitted: list[str],
        history: pd.DataFrame | None,
        ops: list[Op],
    ) -> dict[str, WellState]:
        """A state per well around its learner, its ``AddWell`` op appended to ``ops``: a
        restored well takes its checkpoint's place in the learning order and side-car, a well
        fitted on the history seeds its drift reference from it."""
        now = time.time_ns()
        by_well = (
            {str(w): g for w, g in history.groupby("well", sort=False)}
            if history is not None and not history.empty
            else {}
        )
        wells: dict[str, WellState] = {}
        for well in names:
            origin = "history" if well in fitted else "config/store"
            ops.append(AddWell(well=well, created_ns=now, origin=origin))
            st = WellState(
                well, learners[well], self.settings, self.worker_of(well), self.learning.pools
            )
            row = checkpoints.get(well)
            if row is not None:
                st.learn_seq = row.learn_seq
                self.checkpoints.restore_side_car(st, row.extra)
            elif well in fitted and by_well:
                self._seed_drift_reference(st, by_well[well])
                st.prime_sensor_faults(_priming_rows(by_well[well]))
            wells[well] = st
        return wells

    def _restore_field(
        self, names: list[str]
    ) -> tuple[dict[str, Learner], dict[str, CheckpointRow]]:
        """The field-wide learner from its newest usable snapshot (or a new one), a facade per
        well, and per well restored a checkpoint row whose ``learn_seq`` is what the snapshot
        holds of that well (its side-car from the well's own latest row, if usable)."""
        cfg = self.settings
        configured = cfg.model.full_name
        spec = configured_spec(cfg)
        rows: dict[str, CheckpointRow] = {}
        for well in names:
            row = self.store.latest_checkpoint(well)
            ok, why = usable(row, spec, configured) if row else (False, "")
            if why:
                logger.info("%s: %s", well, why)
            if row is not None and ok:
                rows[well] = row
            elif row is not None:
                logger.warning(
                    "The store holds a %s/%s model for %s but the config asks for %s/%s; building "
                    "the field-wide model from the history and every stored measurement.",
                    row.model,
                    row.method,
                    well,
                    configured,
                    cfg.model.method,
                )
        field: FieldLearner | None = None
        for row in sorted(rows.values(), key=lambda r: r.created_ns, reverse=True):
            try:
                field = FieldLearner.restore(row.blob, train=train_settings(cfg.model))
                logger.info(
                    "Field-wide %s restored from the snapshot in the checkpoint of %s "
                    "(version %d, %d well(s)).",
                    field.name,
                    row.well,
                    field.version,
                    len(field.wells),
                )
                break
            except VFMError as exc:
                logger.warning(
                    "Field snapshot in the checkpoint of %s unusable (%s); trying an older one.",
                    row.well,
                    exc,
                )
        self._field_restored = field
        field = new_field(cfg.model, field)
        known = set(field.wells)
        field.add(names)
        learners: dict[str, Learner] = {w: field.well(w) for w in names}
        checkpoints: dict[str, CheckpointRow] = {}
        if not rows or not known:
            return learners, checkpoints
        base = max(rows.values(), key=lambda r: r.created_ns)
        for well in names:
            if well not in known:
                continue
            own = rows.get(well)
            checkpoints[well] = replace(
                base,
                well=well,
                learn_seq=field.n_learned.get(well, 0),
                extra=own.extra if own is not None else json.dumps({}),
            )
        return learners, checkpoints

    def _remember_history(
        self, field: FieldLearner, wells: list[str], history: pd.DataFrame
    ) -> None:
        """Wells a restored field does not know: their history rows are remembered (for the
        next retrain) but not fitted, since a fit of the field would discard what it learned."""
        measured = history.loc[target_mask(history, "all")]
        added = []
        for well in wells:
            own = measured[measured[WELL].astype(str) == well]
            if own.empty:
                continue
            field.remember(
                well,
                own[list(INPUT_COLUMNS)].to_numpy(dtype=float),
                own[TARGET].to_numpy(dtype=float),
                pd.DatetimeIndex(own[TIME]).as_unit("ns").asi8,
                (own[SOURCE] == WELL_TEST).to_numpy(),
            )
            added.append(well)
        if added:
            logger.warning(
                "%d well(s) of the history are new to the restored field-wide model (%s): they "
                "start at its prior; their history is kept for the next retrain. Delete the "
                "store to fit the whole field on the history again.",
                len(added),
                ", ".join(added[:10]),
            )

    def _restore(self, names: list[str]) -> tuple[dict[str, Learner], dict[str, CheckpointRow]]:
        """A learner per well: from a usable checkpoint, else a new one (priors only)."""
        cfg = self.settings
        learners: dict[str, Learner] = {}
        checkpoints: dict[str, CheckpointRow] = {}
        configured = cfg.model.full_name
        spec = configured_spec(cfg)
        for well in names:
            row = self.store.latest_checkpoint(well)
            ok, why = usable(row, spec, configured) if row else (False, "")
            if why:
                logger.info("%s: %s", well, why)
            if row is not None and ok:
                try:
                    learners[well] = apply_budget(WellLearner.restore(row.blob), cfg.model)
                    checkpoints[well] = row
                    continue
                except VFMError as exc:
                    logger.warning(
                        "Checkpoint of %s unusable (%s); rebuilding it from the store.", well, exc
                    )
            elif row is not None:
                logger.warning(
                    "The store holds a %s/%s model for %s but the config asks for %s/%s; building a new "
                    "model from the history and every stored measurement.",
                    row.model,
                    row.method,
                    well,
                    configured,
                    cfg.model.method,
                )
            learners[well] = new_learner(well, cfg.model)
        return learners, checkpoints

    def _seed_drift_reference(self, st: WellState, own: pd.DataFrame) -> None:
        measured = own[own["q_total"].notna()]
        self.learning.seed_reference(st, measured[list(INPUT_COLUMNS)].to_numpy(dtype=float))

    def _relearn_all(
        self, states: list[WellState], ops: list[Op], merged: bool = False
    ) -> dict[str, int]:
        """Re-learn what the store learned after each well's checkpoint (well by well, or
        with ``merged`` every well's rows in time order, each well's in its learning order);
        refill the rolling errors. Returns how many were re-learned per well."""
        todo = [(st, self.store.learned_after(st.well, st.learn_seq)) for st in states]
        lists = [[(st, r) for r in rows] for st, rows in todo]
        steps: Iterable[tuple[WellState, LearnedRow]] = (
            # by time across the wells; each well's rows keep their learning order
            heapq.merge(*lists, key=lambda step: step[1].time_ns)
            if merged
            else (step for rows in lists for step in rows)
        )
        for st, row in steps:
            self.learning.apply(st, row.sample, row.q_total, row.time_ns, ops, row.source)
            st.learn_seq = row.learn_seq
        for st in states:
            since = int(st.model_changes[-1]["version_after"]) if st.model_changes else None
            for err in self.store.recent_errors(st.well, self.settings.rolling_window, since):
                if err.predicted is not None and err.measured:
                    st.errors.append(abs(err.predicted - err.measured) / abs(err.measured))
        return {st.well: len(rows) for st, rows in todo}

    def _load_recent(self, st: WellState) -> None:
        st.recent.extend(self.store.recent_samples(st.well, RECENT_SAMPLES))
        if st.recent:
            st.last_time_ns = st.recent[-1].time_ns
            st.last_inputs = st.recent[-1].inputs
        now = time.monotonic()
        for p in self.store.pending(st.well):
            st.pending.append(Pending(p.time_ns, p.source, p.q_total, p.via, now))


#: the history a fresh well's instrument-fault detectors are primed on: its last
#: ``PRIME_DAYS`` days, at most ``PRIME_ROWS`` rows (a year of daily changes is the drift
#: test's reference; at one sample a minute the cap keeps start-up to seconds a well)
PRIME_DAYS = 400
PRIME_ROWS = 100_000


def _priming_rows(own: pd.DataFrame) -> pd.DataFrame:
    """A well's history rows for :meth:`WellState.prime_sensor_faults`, in time order: the
    last :data:`PRIME_DAYS` days, at most :data:`PRIME_ROWS` rows."""
    rows = own.sort_values("time", kind="stable")
    times = pd.to_datetime(rows["time"], utc=True)
    if len(times):
        rows = rows[(times >= times.iloc[-1] - pd.Timedelta(days=PRIME_DAYS)).to_numpy()]
    return rows.tail(PRIME_ROWS)


def _fit_fresh(
    learners: dict[str, Learner], fresh: list[str], history: pd.DataFrame, cfg: ModelSettings
) -> list[str]:
    """Fit the wells without a checkpoint on the history; returns the wells fitted. The
    well-by-well fallback of :func:`fit_history` replaces learners: they are kept."""
    started = time.perf_counter()
    subset = {w: learners[w] for w in fresh}
    fitted = fit_history(subset, history, cfg)
    learners.update(subset)
    if fitted:
        logger.info(
            "Fitted %d well(s) on the history in %.1f s.",
            len(fitted),
            time.perf_counter() - started,
        )
    return fitted
