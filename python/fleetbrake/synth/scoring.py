"""A warehouse's flags scored against a synthetic fleet's truth: precision and recall per
class, and how long after an anomaly began its flag did.

A flag is *true* when it overlaps an injected anomaly of its kind on its wagon. An anomaly
counts for the recall when the data can show it: a sensor fault with at least a minute of
ingested samples inside it, a brake anomaly (dragging, weak) with at least five minutes
outside its wagon's sensor faults. A found anomaly's *delay* is from its start to the start of
the earliest flag that overlaps it (0 when a flag began before it).

::

    from fleetbrake.synth.scoring import score_flags

    score = score_flags("fleet.duckdb", load_truth("fleet"))
    score.precision, score.recall, score.by_kind["weak_brake"].delays_s
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fleetbrake.synth.truth import Anomaly, FleetTruth

__all__ = ["SCORED_KINDS", "FlagScore", "KindScore", "score_flags", "wagon_days"]

SCORED_KINDS = ("dragging_brake", "weak_brake", "sensor_fault")
"""The flag kinds the generator injects anomalies of (``overheating`` follows from the
contact temperature and its configured limit, not from an injected fault)."""

OBSERVABLE_SENSOR_S = 60
OBSERVABLE_BRAKE_S = 300


@dataclass
class KindScore:
    """One class: flags raised, true among them, observable anomalies, found among them, and
    the found ones' delays in seconds."""

    flags: int = 0
    true_flags: int = 0
    anomalies: int = 0
    found: int = 0
    delays_s: list[float] = field(default_factory=list)

    @property
    def precision(self) -> float:
        return self.true_flags / self.flags if self.flags else 1.0

    @property
    def recall(self) -> float:
        return self.found / self.anomalies if self.anomalies else 1.0


@dataclass
class FlagScore:
    """Every class together, each class (``by_kind``), and what went wrong in words."""

    by_kind: dict[str, KindScore]
    misses: list[str]

    @property
    def total(self) -> KindScore:
        """Every class summed (its delays pooled)."""
        kinds = self.by_kind.values()
        return KindScore(
            flags=sum(k.flags for k in kinds),
            true_flags=sum(k.true_flags for k in kinds),
            anomalies=sum(k.anomalies for k in kinds),
            found=sum(k.found for k in kinds),
            delays_s=[d for k in kinds for d in k.delays_s],
        )

    @property
    def precision(self) -> float:
        return self.total.precision

    @property
    def recall(self) -> float:
        return self.total.recall


def _overlaps(flag: dict[str, Any], anomaly: Anomaly) -> bool:
    return bool(
        flag["wagon_id"] == anomaly.wagon_id
        and flag["kind"] == anomaly.kind
        and flag["start_utc"] < anomaly.end_utc
        and anomaly.start_utc < flag["end_utc"]
    )


def score_flags(db_path: str | Path, truth: FleetTruth) -> FlagScore:
    """The flags stored in ``db_path`` (every revision's judging leaves one set: the current
    one) against ``truth``'s anomalies (module docstring)."""
    import duckdb

    con = duckdb.connect(str(db_path), read_only=True)
    try:
        flags = con.sql(
            "SELECT flag_id, wagon_id, kind, start_utc, end_utc, evidence FROM v_flags "
            "WHERE list_contains($kinds, kind) ORDER BY start_utc",
            params={"kinds": list(SCORED_KINDS)},
        ).pl()
        observable = [a for a in truth.anomalies if _observable(con, a, truth.anomalies)]
    finally:
        con.close()
    rows = flags.to_dicts()
    by_kind = {kind: KindScore() for kind in SCORED_KINDS}
    misses: list[str] = []
    for f in rows:
        ok = any(_overlaps(f, a) for a in truth.anomalies)
        by_kind[f["kind"]].flags += 1
        by_kind[f["kind"]].true_flags += ok
        if not ok:
            misses.append(f"false {f['kind']} {f['wagon_id']}: {f['evidence']}")
    for a in observable:
        score = by_kind[a.kind]
        score.anomalies += 1
        starts = [f["start_utc"] for f in rows if _overlaps(f, a)]
        if starts:
            score.found += 1
            score.delays_s.append(max((min(starts) - a.start_utc).total_seconds(), 0.0))
        else:
            misses.append(
                f"missed {a.kind} {a.subtype or ''} {a.wagon_id} {a.start_utc}..{a.end_utc}"
            )
    return FlagScore(by_kind=by_kind, misses=misses)


def _observable(con: Any, anomaly: Anomaly, anomalies: list[Anomaly]) -> bool:
    """Whether the ingested samples can show ``anomaly`` (module docstring)."""
    query = "SELECT count(*) FROM samples WHERE wagon_id = $w AND time_utc >= $a AND time_utc < $b"
    params: dict[str, Any] = {"w": anomaly.wagon_id, "a": anomaly.start_utc, "b": anomaly.end_utc}
    if anomaly.kind != "sensor_fault":
        for k, other in enumerate(anomalies):
            if other.kind == "sensor_fault" and other.wagon_id == anomaly.wagon_id:
                query += f" AND NOT (time_utc >= $s{k} AND time_utc < $e{k})"
                params.update({f"s{k}": other.start_utc, f"e{k}": other.end_utc})
    ((count,),) = con.execute(query, params).fetchall()
    need = OBSERVABLE_SENSOR_S if anomaly.kind == "sensor_fault" else OBSERVABLE_BRAKE_S
    return bool(count >= need)


def wagon_days(truth: FleetTruth) -> float:
    """The fleet's registered wagon-days (the false-flag rate's denominator)."""
    return float(truth.config.wagons * truth.config.days)
