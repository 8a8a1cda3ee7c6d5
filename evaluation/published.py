"""Published relation-metric results on the Kümmerle et al. 2009 benchmark, keyed by dataset.

Source: W. Hess, D. Kohler, H. Rapp, D. Andor, "Real-Time Loop Closure in 2D LIDAR SLAM",
ICRA 2016, Table II (Cartographer and Graph Mapping, the latter quoted from Kümmerle et al. 2009)
and Table IV (loop-closure precision), as transcribed in ``../shared/data/PUBLISHED_RESULTS.md``
§1a (a test checks these values against that file). Each value is ``(mean, std)``; units:
m, m², deg, deg². The fr-clinic relations of the benchmark are the *local* hospital set.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["PUBLISHED", "LOOP_PRECISION", "DATASET_NAMES", "recognise_dataset", "published_for", "METRIC_KEYS"]

# metric key → (label in PUBLISHED_RESULTS.md Table II, our RelationResult attribute pair)
METRIC_KEYS: dict[str, tuple[str, str, str]] = {
    "trans": ("abs. transl.", "trans_mean", "trans_std"),
    "trans_sq": ("sq. transl.", "trans_sq_mean", "trans_sq_std"),
    "rot": ("abs. rot.", "rot_mean_deg", "rot_std_deg"),
    "rot_sq": ("sq. rot.", "rot_sq_mean", "rot_sq_std"),
}

Pair = tuple[float, float]

#: dataset → method → metric key → (mean, std)
PUBLISHED: dict[str, dict[str, dict[str, Pair]]] = {
    "aces": {
        "cartographer": {"trans": (0.0375, 0.0426), "trans_sq": (0.0032, 0.0285), "rot": (0.373, 0.469), "rot_sq": (0.359, 3.696)},
        "graph_mapping": {"trans": (0.044, 0.044), "trans_sq": (0.004, 0.009), "rot": (0.4, 0.4), "rot_sq": (0.3, 0.8)},
    },
    "intel": {
        "cartographer": {"trans": (0.0229, 0.0239), "trans_sq": (0.0011, 0.0040), "rot": (0.453, 1.335), "rot_sq": (1.986, 23.988)},
        "graph_mapping": {"trans": (0.031, 0.026), "trans_sq": (0.002, 0.004), "rot": (1.3, 4.7), "rot_sq": (24.0, 166.1)},
    },
    "mit-killian": {
        "cartographer": {"trans": (0.0395, 0.0488), "trans_sq": (0.0039, 0.0144), "rot": (0.352, 0.353), "rot_sq": (0.248, 0.610)},
        "graph_mapping": {"trans": (0.050, 0.056), "trans_sq": (0.006, 0.029), "rot": (0.5, 0.5), "rot_sq": (0.9, 0.9)},
    },
    "mit-csail": {
        "cartographer": {"trans": (0.0319, 0.0363), "trans_sq": (0.0023, 0.0099), "rot": (0.369, 0.365), "rot_sq": (0.270, 0.637)},
        "graph_mapping": {"trans": (0.004, 0.009), "trans_sq": (0.0001, 0.0005), "rot": (0.05, 0.08), "rot_sq": (0.01, 0.04)},
    },
    "fr079": {
        "cartographer": {"trans": (0.0452, 0.0354), "trans_sq": (0.0033, 0.0055), "rot": (0.538, 0.718), "rot_sq": (0.804, 3.627)},
        "graph_mapping": {"trans": (0.056, 0.042), "trans_sq": (0.005, 0.011), "rot": (0.6, 0.6), "rot_sq": (0.7, 1.7)},
    },
    "fr-clinic": {  # Freiburg hospital, local relations
        "cartographer": {"trans": (0.1078, 0.1943), "trans_sq": (0.0494, 0.2831), "rot": (0.747, 2.047), "rot_sq": (4.745, 40.081)},
        "graph_mapping": {"trans": (0.143, 0.180), "trans_sq": (0.053, 0.272), "rot": (0.9, 2.2), "rot_sq": (5.5, 46.2)},
    },
}

#: Hess et al. 2016 Table IV: Cartographer's self-scored loop-closure precision and constraint count.
LOOP_PRECISION: dict[str, tuple[int, float]] = {
    "aces": (971, 0.981),
    "intel": (5786, 0.972),
    "mit-killian": (916, 0.934),
    "mit-csail": (1857, 0.941),
    "fr079": (412, 0.998),
    "fr-clinic": (554, 0.773),
}

#: Row names used in PUBLISHED_RESULTS.md Table II.
DATASET_NAMES: dict[str, str] = {
    "aces": "Aces",
    "intel": "Intel",
    "mit-killian": "MIT Killian Court",
    "mit-csail": "MIT CSAIL",
    "fr079": "Freiburg bldg 79",
    "fr-clinic": "Freiburg hospital (local)",
}

_PATTERNS: tuple[tuple[str, str], ...] = (
    (r"aces", "aces"),
    (r"intel", "intel"),
    (r"killian", "mit-killian"),
    (r"csail", "mit-csail"),
    (r"fr[-_]?0?79|freiburg[-_]?0?79", "fr079"),
    (r"clinic|hospital", "fr-clinic"),
)


def recognise_dataset(path: str | Path | None) -> str | None:
    """The benchmark dataset a relations/log file belongs to, from its file name (or None)."""
    if path is None:
        return None
    name = Path(path).name.lower()
    for pat, key in _PATTERNS:
        if re.search(pat, name):
            return key
    return None


def published_for(path_or_key: str | Path | None) -> dict[str, dict[str, Pair]] | None:
    """Published Cartographer / Graph Mapping numbers for a dataset key or a file name."""
    if path_or_key is None:
        return None
    key = path_or_key if isinstance(path_or_key, str) and path_or_key in PUBLISHED else recognise_dataset(path_or_key)
    return PUBLISHED.get(key) if key else None
