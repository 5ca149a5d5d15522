"""Simulated fields whose wells flow to separators: ``vfm simulate --separator [NAME]``.

The paper's case 2 as most fields live it: no well has a meter of its own, well tests come
weeks or months apart, and what is measured every day is the total of the wells that flow
into one separator. :func:`separator_field` turns a field simulated with synchronised
sampling (``simulate_field(sample_every_days=1)``: every well's sensors sampled at 06:00 UTC
every day) into that:

* the wells are shared out among ``separators`` separators in turn (W01 to the first, W02 to
  the second, ...); one separator is named ``name`` (default ``SEP``), several
  ``SEP1``, ``SEP2``, ...; every well row names its separator in the ``separator`` column;
* the wells' daily rows keep their inputs but lose their rates (``q_total``, ``q_gas``,
  ``q_oil``, ``q_water`` empty, ``source`` empty): the per-well rates are hidden;
* well tests stay as they were (``source`` = ``well_test``, their own times);
* at every daily instant, one row per separator: ``source`` = ``separator``, ``well`` = the
  separator's name, ``q_total`` = the sum of its wells' true rates at that instant times
  ``1 + noise * e`` (e standard normal, ``noise`` the relative standard deviation, default
  1.5 %: a separator's or fiscal meter's usual 1-2 %), the input columns empty. A shut-in
  well, or one that has not started yet, has no row and contributes 0 (it is shut in: it
  flows nowhere). No reading is written at an instant when a member well flows but its
  data are missing (a historian gap), because the well's inputs that the reading would
  need are missing too (an operator would not book such a reading for allocation).

The truth stays beside the data as :func:`vfm_core.simulate.write_field` writes it: one
truth row per observation row, the separator rows with ``q_true`` = the true total
(Sm3/h) and the other truth columns empty; ``truth["separators"]`` names each separator's
wells and noise.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pandas as pd

from vfm_core import schema
from vfm_core.errors import ConfigError
from vfm_core.simulate import SimulatedField, simulate_field

__all__ = ["SEPARATOR_NOISE", "separator_field", "simulate_separator_field", "separator_names"]

#: default relative noise (sd) of a separator's total: a separator or fiscal meter's 1-2 %
SEPARATOR_NOISE = 0.015
_SEPARATOR_COLUMN = "separator"
_SEPARATOR_SOURCE = "separator"
_RATE_COLUMNS = (schema.TARGET, *schema.OPTIONAL_RATE_COLUMNS)


def separator_names(name: str, count: int) -> list[str]:
    """The separators' names: ``name`` for one, ``name1`` .. ``nameK`` for several."""
    return [name] if count == 1 else [f"{name}{k + 1}" for k in range(count)]


def simulate_separator_field(
    *,
    separators: int = 1,
    name: str = "SEP",
    noise: float = SEPARATOR_NOISE,
    **simulate: Any,
) -> SimulatedField:
    """Simulate a field (``simulate`` are :func:`vfm_core.simulate.simulate_field`'s
    arguments) with daily synchronised samples and turn it into a separator field (see the
    module docstring and :func:`separator_field`)."""
    field = simulate_field(sample_every_days=1.0, **simulate)
    return separator_field(
        field, separators=separators, name=name, noise=noise, seed=int(simulate.get("seed", 0))
    )


def separator_field(
    field: SimulatedField,
    *,
    separators: int = 1,
    name: str = "SEP",
    noise: float = SEPARATOR_NOISE,
    seed: int = 0,
) -> SimulatedField:
    """``field`` (simulated with ``sample_every_days``) as a separator field: per-well rates
    hidden, one reading per separator and sampling instant (Sm3/h), the truth beside it."""
    obs, samples, truth = field.observations, field.truth_samples, field.truth
    wells = list(truth["wells"])
    if int(separators) != separators or not 1 <= separators <= len(wells):
        raise ConfigError(
            f"separators must be a whole number from 1 to the number of wells ({len(wells)}), "
            f"not {separators!r}."
        )
    if not (math.isfinite(noise) and 0.0 <= noise <= 0.2):
        raise ConfigError(
            f"The separator noise is a relative standard deviation; give a number in 0..0.2 "
            f"(e.g. 0.015 for 1.5 %), not {noise!r}."
        )
    name = str(name).strip()
    if not name or name in wells:
        raise ConfigError(
            f"The separator's name '{name}' is empty or the name of a well; give another "
            f"(e.g. SEP)."
        )
    names = separator_names(name, int(separators))
    member_of = {w: names[j % len(names)] for j, w in enumerate(wells)}

    obs = obs.copy()
    sampled = (obs[schema.SOURCE] != schema.WELL_TEST).to_numpy()
    for column in _RATE_COLUMNS:
        if column in obs.columns:
            obs.loc[sampled, column] = np.nan
    obs.loc[sampled, schema.SOURCE] = ""
    obs[_SEPARATOR_COLUMN] = obs[schema.WELL].map(member_of)

    rows, truth_rows, skipped = _readings(
        obs.loc[sampled], samples.loc[sampled, "q_true"], truth, member_of, noise, seed
    )
    readings = pd.DataFrame(rows, columns=[schema.TIME, schema.WELL, schema.TARGET, schema.SOURCE])
    observations = pd.concat([obs, readings], ignore_index=True)
    truth_samples = pd.concat([samples, pd.DataFrame(truth_rows)], ignore_index=True)
    # (time, well) order, as every frame of the format
    order = np.lexsort((observations[schema.WELL].to_numpy(), observations[schema.TIME].to_numpy()))
    observations = observations.iloc[order].reset_index(drop=True)
    truth_samples = truth_samples.iloc[order].reset_index(drop=True)
    new_truth = dict(truth)
    new_truth["separators"] = {
        sep: {
            "wells": [w for w in wells if member_of[w] == sep],
            "noise_rel": float(noise),
            "readings": int((readings[schema.WELL] == sep).sum()),
        }
        for sep in names
    }
    new_truth["separator_instants_skipped"] = int(skipped)
    new_truth["rows"] = int(len(observations))
    new_truth["rows_per_source"] = {
        (k or "none"): int(v)
        for k, v in observations[schema.SOURCE].value_counts().sort_index().items()
    }
    return replace(field, observations=observations, truth_samples=truth_samples, truth=new_truth)


def _readings(
    daily_rows: pd.DataFrame,
    q_true: pd.Series,
    truth: dict[str, Any],
    member_of: dict[str, str],
    noise: float,
    seed: int,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]], int]:
    """One reading per separator and sampling instant of ``daily_rows`` (the wells' sampled
    rows, ``q_true`` their true rates, Sm3/h): the rows, their truth rows and how many
    instants were skipped (a member well flowing with its data missing)."""
    wells = list(member_of)
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(2,)))
    gaps = {
        w: [(pd.Timestamp(a), pd.Timestamp(b)) for a, b in truth["wells"][w].get("data_gaps", [])]
        for w in wells
    }
    flowing = {w: (pd.Timestamp(truth["wells"][w]["start"]), _shut_ins(truth, w)) for w in wells}
    daily = daily_rows[[schema.TIME, schema.WELL, _SEPARATOR_COLUMN]].assign(
        q_true=q_true.to_numpy()
    )
    rows: list[dict[str, Any]] = []
    truth_rows: list[dict[str, Any]] = []
    skipped = 0
    for (time, sep), group in daily.groupby([schema.TIME, _SEPARATOR_COLUMN], sort=True):
        members = [w for w in wells if member_of[w] == sep]
        present = set(group[schema.WELL])
        if any(
            w not in present and _in_gap(time, gaps[w], flowing[w]) for w in members
        ):  # a member flows but its data are missing: no reading
            skipped += 1
            continue
        total = float(group["q_true"].sum())
        rows.append(
            {
                schema.TIME: time,
                schema.WELL: sep,
                schema.TARGET: total * (1.0 + noise * rng.standard_normal()),
                schema.SOURCE: _SEPARATOR_SOURCE,
            }
        )
        truth_rows.append({schema.TIME: time, schema.WELL: sep, "q_true": total})
    return rows, truth_rows, skipped


def _shut_ins(truth: dict[str, Any], well: str) -> list[tuple[pd.Timestamp, pd.Timestamp]]:
    return [(pd.Timestamp(a), pd.Timestamp(b)) for a, b in truth["wells"][well].get("shut_ins", [])]


def _in_gap(
    time: pd.Timestamp,
    gaps: list[tuple[pd.Timestamp, pd.Timestamp]],
    flowing: tuple[pd.Timestamp, list[tuple[pd.Timestamp, pd.Timestamp]]],
) -> bool:
    """Whether a well that has no row at ``time`` was flowing then (started, not shut in)
    while its data were missing."""
    start, shut = flowing
    if time < start or any(a <= time <= b for a, b in shut):
        return False
    return any(a <= time <= b for a, b in gaps)
