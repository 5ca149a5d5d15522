"""Where ``vfm diagnose`` reads its observations: a source registered under the entry-point
group ``vfm.sources`` (a service's SQLite store), a well's pool (the wells that run the
same model and method), the history a service was fitted on in front of its store, and
the model and method the service runs, from the store's records.

Exported from :mod:`vfm_core.jobs.diagnose` as before; no dependency on it.
"""

from __future__ import annotations

import importlib.metadata

import pandas as pd

from vfm_core.data import target_mask
from vfm_core.effects import resolve_effects
from vfm_core.errors import ConfigError, DataError
from vfm_core.models import EFFECT_MODELS
from vfm_core.schema import TIME, WELL

__all__ = ["load_source", "pool_frame", "with_history", "stored_method", "store_model"]


def load_source(kind: str, path: str, well: str | None = None) -> pd.DataFrame:
    """Observations from a source registered under the entry-point group ``vfm.sources``
    (``store``: a service's SQLite store, ``load_store(path, well)``), checked like a file."""
    from vfm_core.observations import validate_frame

    found = {ep.name: ep for ep in importlib.metadata.entry_points(group="vfm.sources")}
    if kind not in found:
        raise ConfigError(
            f"No data source '{kind}' is installed (entry point group vfm.sources has "
            f"{sorted(found) or 'none'}); install the project with its service package "
            "(pip install -e .) to read a service's store, or export the store to a file."
        )
    try:
        loader = found[kind].load()
    except ImportError as exc:
        raise ConfigError(
            f"The data source '{kind}' ({found[kind].value}) cannot be imported: {exc}."
        ) from None
    frame = loader(path, well)
    if not isinstance(frame, pd.DataFrame):
        raise DataError(f"The data source '{kind}' returned {type(frame).__name__}, not a frame.")
    if frame.empty:
        which = f" for well {well}" if well else ""
        raise DataError(f"The store {path} holds no observations{which}.")
    return validate_frame(frame, name=f"{kind} {path}").frame


def pool_frame(frame: pd.DataFrame, well: str) -> tuple[pd.DataFrame, str]:
    """The rows of ``well`` and of every other well that runs the same model (base model,
    effects and learning method, as the store's checkpoints say: ``attrs["models"]``), and a
    sentence saying which. Without a record of ``well``'s model, every well of the frame."""
    wells = frame[WELL].astype(str)
    if not (wells == well).any():
        raise DataError(f"The data hold no rows of well {well}.")
    stored = frame.attrs.get("models") or {}
    mine = stored.get(well)
    if mine is None:
        pool = sorted(set(wells))
        why = "its model is not recorded, so every well of the data"
    else:
        key = (mine["model"], tuple(mine["effects"]), mine.get("method"))
        pool = sorted(
            w
            for w in set(wells)
            if w in stored
            and (stored[w]["model"], tuple(stored[w]["effects"]), stored[w].get("method")) == key
        )
        why = "the wells that run the same model and method"
    out = frame[wells.isin(pool).to_numpy()].reset_index(drop=True)
    out.attrs = dict(frame.attrs)
    others = [w for w in pool if w != well]
    return out, (
        f"Diagnosing {well} beside its pool ({why}): "
        + (", ".join(others[:10]) + (" ..." if len(others) > 10 else "") if others else "none")
        + "."
    )


def with_history(
    frame: pd.DataFrame, history: pd.DataFrame, until: str | pd.Timestamp
) -> tuple[pd.DataFrame, pd.Timestamp, str]:
    """A service's store with the history it was fitted on in front: the history file's rows
    of the store's wells before ``until`` (the service's ``model.history_until``) and the
    store's rows from ``until`` on. Diagnosed with the split at ``until``, the replay starts
    where the service started (the same fit on the same rows) and learns the same
    measurements, so its baseline is the error the service ran at (not a fresh fit on the
    store's first months). Returns the frame (the store's ``attrs`` kept), the split and a
    sentence saying what was joined."""
    ts = pd.Timestamp(until)
    ts = ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")
    wells = set(frame[WELL].astype(str))
    old = history[
        (history[TIME] < ts).to_numpy() & history[WELL].astype(str).isin(wells).to_numpy()
    ]
    old = old[[c for c in old.columns if c in frame.columns]]
    new = frame[(frame[TIME] >= ts).to_numpy()]
    dropped = len(frame) - len(new)
    out = pd.concat([old, new], ignore_index=True).sort_values([TIME, WELL], kind="stable")
    out = out.reset_index(drop=True)
    out.attrs = dict(frame.attrs)
    measured = int(target_mask(old, "all").sum()) if len(old) else 0
    note = (
        f"The history the service was fitted on ({measured:,} measurements of these wells "
        f"before {ts.date()}) is joined in front of the store, and the replay starts at "
        f"{ts.date()}, where the service started: its baseline is the error the service ran at."
    )
    if dropped:
        note += f" ({dropped:,} stored rows before {ts.date()} are left out: the history has them.)"
    return out, ts, note


def stored_method(frame: pd.DataFrame, well: str | None) -> str | None:
    """The learning method the service runs for ``well`` (or for every well of the frame,
    when they agree), from the store's checkpoints; None when not recorded."""
    stored = frame.attrs.get("models") or {}
    if well is not None:
        return (stored.get(well) or {}).get("method")
    methods = {r.get("method") for w, r in stored.items() if w in set(frame[WELL].astype(str))}
    return next(iter(methods)) if len(methods) == 1 else None


def store_model(
    frame: pd.DataFrame, model: str | None, given_base: list[str] | None, base: list[str]
) -> tuple[str, list[str]]:
    """The base model and effects of ``vfm diagnose --store``: what the user gave, else the
    model the service runs for the wells diagnosed (their latest checkpoints, in the
    frame's ``attrs["models"]``), said in one line; ``mm`` when they run no physics model
    or different ones."""
    stored = frame.attrs.get("models") or {}
    wells = sorted(set(frame[WELL].astype(str)))
    runs = {w: stored[w] for w in wells if w in stored}
    kinds = {(r["model"], tuple(r["effects"])) for r in runs.values()}
    if len(kinds) != 1:
        if len(kinds) > 1:
            print(
                f"The wells run different models ({', '.join(sorted('+'.join([m, *e]) for m, e in kinds))}); "
                f"diagnosing {'+'.join([model or 'mm', *base])} (give --well to start from one "
                "well's model)."
            )
        return model or "mm", base
    name, effects = next(iter(kinds))
    running = "+".join([name, *effects])
    if name not in EFFECT_MODELS:
        if model is None:
            print(f"The service runs {running}, not a physics model: diagnosing mm.")
        return model or "mm", base
    chosen = model or name
    if given_base is None and chosen == name:
        resolve_effects(list(effects))  # an effect the store names must still be importable
        print(
            f"The service runs {running}: the diagnosis starts from it and looks for what is "
            "still missing (--model and --base-effects none for another start)."
        )
        return chosen, list(effects)
    if (chosen, base) != (name, list(effects)):
        print(f"The service runs {running}; diagnosing {'+'.join([chosen, *base])} as asked.")
    return chosen, base
