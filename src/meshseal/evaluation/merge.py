"""`meshseal eval --json` results of slices of one split (`--start S --meshes N`, a process each) added
up into one: what a single run over all their meshes would report, each rate weighted by the pictures
it was measured on.

Counts add; rates, means and seconds are averaged with their pictures as weights (a rate that a slice
could not measure, None, is left out of that average); a 95th percentile cannot be recovered from the
slices' own, so the merged `flip_object_p95` is the largest of theirs (an upper bound: a target of the
form "p95 at most X" that it meets is met).
"""

from __future__ import annotations

# What names the run rather than measures it: the same in every slice, kept as it is.
RUN_KEYS = ("model", "split", "sampler", "protocol", "texture_kinds", "size", "n_views", "light_gain", "max_flip", "strength_asked",
            "fpr_threshold")
COUNT_KEYS = ("n_meshes",)
UPPER_KEYS = ("flip_object_p95",)


def _weighted(rows: list[tuple[dict, float]], key: str):
    """The mean of `key` over rows (dict, weight) that have it (not None), weighted; None if none has it."""
    have = [(row[key], weight) for row, weight in rows if row.get(key) is not None]
    total = sum(weight for _, weight in have)
    if not have or total <= 0:
        return None
    return sum(value * weight for value, weight in have) / total


def _numeric(rows: list[dict], key: str) -> bool:
    """Whether every value of `key` the rows have (not None) is a number, and one has it."""
    values = [row[key] for row in rows if row.get(key) is not None]
    return bool(values) and all(isinstance(value, (int, float)) and not isinstance(value, bool) for value in values)


def _merge_rows(rows: list[dict]) -> dict:
    """Rows of one table (each with `pictures`) added up: pictures summed, the rest weighted by them."""
    weighted = [(row, float(row.get("pictures", 0))) for row in rows]
    merged = {"pictures": sum(int(row.get("pictures", 0)) for row in rows)}
    for key in dict.fromkeys(key for row in rows for key in row):
        if key == "pictures":
            continue
        if _numeric(rows, key):
            merged[key] = _weighted(weighted, key)
        elif any(row.get(key) is not None for row in rows):
            merged[key] = next(row[key] for row in rows if row.get(key) is not None)
    return merged


def merge_results(parts: list[dict]) -> dict:
    """One `meshseal eval --json` result from those of slices of the same run (same model, attacks,
    views and settings; their `start`s say which meshes each read). Raises ValueError where the
    parts do not belong to one run."""
    if not parts:
        raise ValueError("nothing to merge")
    for key in ("model", "split", "sampler", "size", "n_views", "max_flip"):
        values = {repr(part.get(key)) for part in parts}
        if len(values) > 1:
            raise ValueError(f"the slices differ in {key}: {', '.join(sorted(values))}")
    pictures = [float(part.get("n_meshes", 0)) * float(part.get("n_views", 1)) for part in parts]
    merged = {key: parts[0][key] for key in RUN_KEYS if key in parts[0]}
    merged["start"] = min(int(part.get("start", 0)) for part in parts)
    merged["slices"] = sorted([int(part.get("start", 0)), int(part.get("n_meshes", 0))] for part in parts)
    for key in COUNT_KEYS:
        merged[key] = sum(int(part.get(key, 0)) for part in parts)
    for key in UPPER_KEYS:
        values = [part[key] for part in parts if part.get(key) is not None]
        if values:
            merged[key] = max(values)
    for key in dict.fromkeys(key for part in parts for key in part):
        if key in merged or key in RUN_KEYS or key in ("start", "slices"):
            continue
        if _numeric(parts, key):
            merged[key] = _weighted(list(zip(parts, pictures)), key)
    for table in ("attacks", "by_kind", "by_uv_map"):
        names = list(dict.fromkeys(name for part in parts for name in part.get(table) or {}))
        if names:
            merged[table] = {name: _merge_rows([part[table][name] for part in parts if name in (part.get(table) or {})])
                             for name in names}
    items = {}
    for part in parts:
        items.update(part.get("by_item") or {})
    if items:
        merged["by_item"] = items
    return merged
