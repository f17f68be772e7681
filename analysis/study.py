"""The study's analysis: every item x stimulus set, by the sound procedure and the paper's.

* ``rm`` (default, sound): ratings averaged per participant x condition; one-way
  repeated-measures ANOVA (Greenhouse-Geisser p as the headline, since Mauchly's test has
  little power with few participants), paired t-tests with Holm correction, Friedman test,
  and the mixed-model F on all ratings as a check.
* ``paper`` (replication only): one-way between-subjects ANOVA on all individual ratings
  pooled as independent, then Tukey HSD - the procedure the paper's p-values fit. It
  ignores the repeated-measures design (pseudo-replication) and is labelled so everywhere.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pandas as pd

import facelab.analysis.stats as stats
from facelab.errors import AnalysisError
from facelab.protocol import Protocol

__all__ = ["METHODS", "StudyResults", "analyze_study", "bracket_pairs"]

METHODS = {
    "rm": "repeated-measures ANOVA on participant means (GG-corrected), paired t-tests with Holm",
    "paper": "the paper's procedure: one-way ANOVA on pooled ratings + Tukey HSD "
    "(pseudo-replicated: treats repeated ratings as independent)",
}
ALPHA = 0.05


@dataclass(frozen=True)
class StudyResults:
    """Tidy tables, each with ``item`` and ``stimulus_set`` first."""

    method: str
    ratings: pd.DataFrame  # every rating analysed (the loaded logs, tidy)
    cells: pd.DataFrame  # participant x condition means
    rm_anova: pd.DataFrame
    pairwise: pd.DataFrame
    friedman: pd.DataFrame
    lmm: pd.DataFrame
    paper_anova: pd.DataFrame
    paper_tukey: pd.DataFrame
    layout: pd.DataFrame  # the paper's layout, both procedures, beside reported values
    notes: tuple[str, ...] = ()  # what was left out of which analysis, and why

    def tables(self) -> dict[str, pd.DataFrame]:
        return {
            "ratings": self.ratings,
            "cell_means": self.cells,
            "rm_anova": self.rm_anova,
            "pairwise_paired": self.pairwise,
            "friedman": self.friedman,
            "lmm_anova": self.lmm,
            "paper_anova": self.paper_anova,
            "paper_tukey": self.paper_tukey,
            "paper_layout": self.layout,
        }


def _tag(frame: pd.DataFrame, item: str, stimulus_set: str) -> pd.DataFrame:
    frame = frame.copy()
    frame.insert(0, "stimulus_set", stimulus_set)
    frame.insert(0, "item", item)
    return frame


def _pairs_text(pairs: pd.DataFrame, p_col: str) -> str:
    sig = pairs[pairs[p_col] < ALPHA]
    return "; ".join(f"{r.a}-{r.b} p={getattr(r, p_col):.4f}" for r in sig.itertuples()) or "none"


def _layout_row(
    common: dict, *, procedure: str, anova: pd.DataFrame, p: float, pairs: pd.DataFrame
) -> dict:
    """One row of the paper-layout table: ANOVA F, df, p, and the pairs below .05."""
    return {
        "item": common["item"],
        "stimulus_set": common["stimulus_set"],
        "procedure": procedure,
        "n_participants": common["n_participants"],
        "df1": anova.df1[0],
        "df2": anova.df2[0],
        "f": anova.f[0],
        "anova_p": p,
        "pairs_p_lt_05": _pairs_text(pairs, "p_adj"),
        "reported_anova_p": common["reported_anova_p"],
        "reported_pairs": common["reported_pairs"],
    }


def _not_estimable(common: dict, *, procedure: str, reason: str) -> dict:
    """A paper-layout row whose test cannot be computed (a pilot of one participant)."""
    nan = float("nan")
    return {
        "item": common["item"],
        "stimulus_set": common["stimulus_set"],
        "procedure": procedure,
        "n_participants": common["n_participants"],
        "df1": nan,
        "df2": nan,
        "f": nan,
        "anova_p": nan,
        "pairs_p_lt_05": reason,
        "reported_anova_p": common["reported_anova_p"],
        "reported_pairs": common["reported_pairs"],
    }


def bracket_pairs(results: StudyResults, *, item: str, stimulus_set: str) -> pd.DataFrame:
    """Pairs with the corrected p-values of the primary method (``a, b, p``) for figures."""
    if results.method == "paper":
        table, col = results.paper_tukey, "p_adj"
    else:
        table, col = results.pairwise, "p_adj"
    if table.empty or "a" not in table:  # no test was estimable (a pilot): no brackets
        return pd.DataFrame(columns=["a", "b", "p"])
    sel = table[(table["item"] == item) & (table["stimulus_set"] == stimulus_set)
                & table["a"].notna()]  # fmt: skip
    return sel[["a", "b", col]].rename(columns={col: "p"}).reset_index(drop=True)


@dataclass(frozen=True)
class RatingCell:
    """One item x stimulus set of the VAS ratings as the primary analysis takes it: ``sub``
    its ratings (condition categorical in protocol order; None when fewer than two
    conditions were rated), ``seen`` the conditions rated, ``rm_sub`` the ratings of the
    participants who rated every one of them (the repeated-measures rows), ``notes`` what
    was left out and why."""

    item: Any
    sset: Any
    where: str
    sub: pd.DataFrame | None
    seen: list[str]
    rm_sub: pd.DataFrame | None
    notes: tuple[str, ...]


def rating_cells(data: pd.DataFrame, protocol: Protocol) -> Iterator[RatingCell]:
    """Every item x stimulus set with VAS ratings in ``data``, selected as ``facelab analyze``
    selects them (and ``facelab power --simulate``: one path): VAS screens only, a cell with
    one condition not analysed, participants lacking a condition left out of the repeated-
    measures rows (kept in the pooled procedure)."""
    order = [c.id for c in protocol.conditions]
    data = data[data["screen"].fillna("vas") == "vas"]
    for item in protocol.items:
        for sset in protocol.stimulus_sets:
            sub = data[(data["item"] == item.id) & (data["stimulus_set"] == sset.id)]
            if sub.empty:
                continue
            where = f"{item.id} / {sset.id}"
            seen = [c for c in order if c in set(sub["condition"])]
            if len(seen) < 2:
                why = f"{where}: responses for {len(seen)} condition(s) only; not analysed."
                yield RatingCell(item, sset, where, None, seen, None, (why,))
                continue
            sub = sub.assign(condition=pd.Categorical(sub["condition"], categories=seen))
            per = sub.groupby("participant")["condition"].nunique()
            partial = sorted(per[per < len(seen)].index)
            notes = (
                (f"{where}: participant(s) {', '.join(map(str, partial))} lack a condition; "
                 "left out of the repeated-measures analysis (kept in the pooled procedure).",)
                if partial else ()
            )  # fmt: skip
            yield RatingCell(item, sset, where, sub, seen,
                             sub[~sub["participant"].isin(partial)], notes)  # fmt: skip


def analyze_study(data: pd.DataFrame, protocol: Protocol, *, method: str = "rm") -> StudyResults:
    """Run both procedures for every item x stimulus set present in ``data``.

    ``method`` picks the primary procedure (figures' brackets, headline); both are computed
    so the report can show them side by side.
    """
    if method not in METHODS:
        raise AnalysisError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    order = [c.id for c in protocol.conditions]
    unknown = sorted(set(data["condition"]) - set(order))
    if unknown:
        raise AnalysisError(f"conditions in the logs but not in the protocol: {', '.join(unknown)}")
    data = data[data["screen"].fillna("vas") == "vas"]
    notes: list[str] = []
    out: dict[str, list[pd.DataFrame]] = {
        k: [] for k in ("cells", "rm", "pw", "fr", "lmm", "pa", "tk", "layout")
    }
    reported = {
        (t.item, t.stimulus_set): t
        for t in (protocol.reported_results.tests if protocol.reported_results else [])
    }
    for cell in rating_cells(data, protocol):
        item, sset, where = cell.item, cell.sset, cell.where
        # a study of one condition (a pilot of one method); a cell that lacks the others of a
        # study of several is "not analysed" (rating_cells' note)
        one_condition = cell.sub is None and len(protocol.conditions) == 1
        if not one_condition:
            notes.extend(cell.notes)
        if cell.sub is None and not one_condition:
            continue
        if one_condition:  # a pilot of one method: its ratings described, nothing compared
            sub = data[(data["item"] == item.id) & (data["stimulus_set"] == sset.id)]
            seen = cell.seen
            sub = sub.assign(condition=pd.Categorical(sub["condition"], categories=seen))
            n_rm = int(sub["participant"].nunique())
            estimable = False
            reason = "not estimable: ratings for one condition only, nothing to compare"
        else:
            sub, seen, rm_sub = cell.sub, cell.seen, cell.rm_sub
            n_rm = int(rm_sub["participant"].nunique())
            estimable = n_rm >= 2
            reason = (
                f"not estimable: {n_rm} participant(s) rated every condition; the "
                "repeated-measures analysis needs 2 or more"
            )
        kw = {"dv": "rating", "within": "condition", "subject": "participant"}
        fr = pd.DataFrame()
        why: dict[str, str] = {}  # a test's table without a row: its row says why instead
        if estimable and len(seen) >= 3:  # ranks: defined when F is not (no residual variance)
            try:
                fr = stats.friedman(rm_sub, **kw)
            except AnalysisError as exc:
                why["fr"] = f"not estimable: {exc}"
                notes.append(f"{where}: Friedman's test is not estimable ({exc}).")
        elif estimable:
            why["fr"] = (f"not estimable: Friedman's test needs three or more conditions, "
                         f"{len(seen)} were rated (the paired comparison is its test)")  # fmt: skip
            notes.append(f"{where}: {why['fr']}.")
        if estimable:
            try:
                wide = stats.cell_means(rm_sub, **kw)
                rm = stats.rm_anova(rm_sub, **kw)
                pw = stats.pairwise_paired(rm_sub, **kw, padjust="holm")
                lmm = stats.lmm_anova(rm_sub, **kw)
            except AnalysisError as exc:  # e.g. ratings without any variation
                estimable, reason = False, f"not estimable: {exc}"
            else:
                cells = wide.reset_index().melt(
                    id_vars="s", var_name="condition", value_name="mean"
                ).rename(columns={"s": "participant"})
        if not estimable:  # a pilot: descriptive cells, the inferential rows not estimable
            kept = "; Friedman's rank test is reported" if not fr.empty else ""
            notes.append(f"{where}: {reason} (descriptive tables and figures only{kept}).")
            rm = pw = lmm = pd.DataFrame()
            why = {"fr": reason, **why, "rm": reason, "pw": reason, "lmm": reason}
            cells = (
                sub.groupby(["participant", "condition"], observed=True)["rating"]
                .mean()
                .rename("mean")
                .reset_index()
            )
        pa = tk = pd.DataFrame()
        if not one_condition and sub["participant"].nunique() < 2:
            notes.append(f"{where}: the paper's procedure has one participant's ratings: its "
                         "F and pairs test how this person rated the conditions, not a "
                         "difference in people.")  # fmt: skip
        if not one_condition:
            try:
                pa = stats.one_way_anova(sub, dv="rating", between="condition")
                tk = stats.tukey_hsd(sub, dv="rating", between="condition")
            except AnalysisError as exc:
                notes.append(f"{where}: the paper's procedure is not estimable ({exc}).")
                pa = tk = pd.DataFrame()
                why |= {"pa": f"not estimable: {exc}", "tk": f"not estimable: {exc}"}
        for key, frame in (
            ("cells", cells),
            ("rm", rm),
            ("pw", pw),
            ("fr", fr),
            ("lmm", lmm),
            ("pa", pa),
            ("tk", tk),
        ):
            if frame.empty and key in why:  # the CSV says why this cell has no test
                frame = pd.DataFrame([{"note": why[key]}])
            out[key].append(_tag(frame, item.id, sset.id))
        rep = reported.get((item.id, sset.id))
        rep_pairs = "; ".join(f"{p.a}-{p.b} p={p.p:.4f}" for p in rep.pairs) if rep else ""
        common = {
            "item": item.id,
            "stimulus_set": sset.id,
            "n_participants": n_rm,
            "reported_anova_p": rep.anova_p if rep else float("nan"),
            "reported_pairs": rep_pairs,
        }
        rows = [
            _layout_row(common, procedure="rm", anova=rm, p=rm.p_gg[0], pairs=pw)
            if estimable
            else _not_estimable(common, procedure="rm", reason=reason),
            _layout_row(common, procedure="paper", anova=pa, p=pa.p[0], pairs=tk)
            if not pa.empty
            else _not_estimable(common, procedure="paper", reason="not estimable"),
        ]
        out["layout"].append(pd.DataFrame(rows))
    if not out["layout"]:
        raise AnalysisError(
            "no VAS ratings match the protocol's items and stimulus sets (the logs hold "
            f"items {', '.join(map(str, sorted(set(data['item'])))) or 'none'})"
        )

    def cat(key: str) -> pd.DataFrame:
        frames = [f for f in out[key] if not f.empty]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()

    ratings = data.drop(columns=["source"], errors="ignore").assign(
        condition=data["condition"].astype(str)
    )
    return StudyResults(
        method=method,
        ratings=ratings.reset_index(drop=True),
        cells=cat("cells"),
        rm_anova=cat("rm"),
        pairwise=cat("pw"),
        friedman=cat("fr"),
        lmm=cat("lmm"),
        paper_anova=cat("pa"),
        paper_tukey=cat("tk"),
        layout=cat("layout"),
        notes=tuple(notes),
    )
