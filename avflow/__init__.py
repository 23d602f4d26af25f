"""avflow: debris-avalanche scenarios with the kinetic Saint-Venant scheme of
Mangeney-Castelnau et al. (2003), with Dirac stopping under the Coulomb threshold.

Public API:

- :func:`load_scenario` reads and validates a scenario YAML file;
- :func:`run` runs a scenario (a path or a loaded scenario) and returns a CF ``xarray.Dataset``.
"""

__version__ = "0.1.0"

from avflow.errors import AvflowError, ScenarioError  # noqa: E402
from avflow.scenario import load_scenario  # noqa: E402


def run(scenario, progress=None, max_memory=None):
    """Run a scenario (path or :class:`~avflow.scenario.schema.Scenario`) and return its Dataset.

    ``max_memory`` (bytes or "8G"): refuse a run estimated to need more (default
    ``$AVFLOW_MAX_MEMORY``, else half the machine's memory); a run that blows up raises
    :class:`avflow.errors.RunFailed`.
    """
    from avflow.output.dataset import to_dataset
    from avflow.simulation.runner import simulate

    if not hasattr(scenario, "terrain"):
        scenario = load_scenario(scenario)
    return to_dataset(simulate(scenario, progress=progress, max_memory=max_memory))


__all__ = ["__version__", "AvflowError", "ScenarioError", "load_scenario", "run"]
