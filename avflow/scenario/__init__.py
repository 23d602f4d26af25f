"""Stage 1, the scenario: YAML -> a validated, frozen, hashed :class:`Scenario`.

- :mod:`avflow.scenario.yamlio`: YAML 1.2 core scalars with the line:column of every key;
- :mod:`avflow.scenario.schema`: the pydantic schema, its one-line errors and the hash.
"""

from avflow.scenario.schema import Scenario, load_scenario, parse_scenario, write_json_schema

__all__ = ["Scenario", "load_scenario", "parse_scenario", "write_json_schema"]
