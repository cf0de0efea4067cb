"""The default suite runs nothing its report does not use."""

from __future__ import annotations

import integrators
from benchmarks import suites
from problems.spec import parse_value, split_spec


def test_no_integrator_of_the_default_suite_spells_out_a_default_option():
    # The report keys methods by the spec as written: "genalpha:rho_inf=0.5" (the
    # default) is genalpha under a second name, a second curve and a second compilation
    # for a method the suite already runs.
    spelled = set()
    for run in suites.load("default").runs:
        key, given = split_spec(str(run.integrator))
        defaults = integrators.make(key).options()
        spelled |= {f"{run.integrator} ({name} is the default)" for name, text in given.items()
                    if parse_value(text, defaults[name], name) == defaults[name]}
    assert not spelled
