"""The configuration says what each setting does; which log chose its default is in docs/, not in the
config: a rule written for one log's failure must not read as if it were about that log."""

from __future__ import annotations

import inspect
import re

from pydantic import BaseModel

from slam.pipeline.config import SlamConfig

# The logs of the development set and of the benchmarks, by the names a description would use.
LOG_NAMES = re.compile(r"\b(intel|csail|hospital|freiburg|fr-clinic|killian|mines|paristech|malaga|málaga|almer[ií]a|"
                       r"ual|loop5|robot4|brenner|acapulco|belgioioso|fhw|orebro|örebro|kitti|aces|fr079)\b", re.I)


def _texts(model: type[BaseModel], seen: set[type]) -> list[tuple[str, str]]:
    if model in seen:
        return []
    seen.add(model)
    out = [(model.__name__, inspect.getdoc(model) or "")]
    for name, field in model.model_fields.items():
        out.append((f"{model.__name__}.{name}", field.description or ""))
        for arg in (field.annotation, *getattr(field.annotation, "__args__", ())):
            if isinstance(arg, type) and issubclass(arg, BaseModel):
                out += _texts(arg, seen)
    return out


def test_no_config_description_names_a_log():
    texts = _texts(SlamConfig, set())
    assert len(texts) > 100  # every section and field was reached
    offenders = [(where, m.group(0)) for where, text in texts for m in [LOG_NAMES.search(text)] if m]
    assert offenders == []


def test_the_check_finds_a_log_name():
    assert LOG_NAMES.search("a window chosen for one Intel revisit")
    assert not LOG_NAMES.search("the overlap distance of the sensor (upper quartile of the ranges)")
