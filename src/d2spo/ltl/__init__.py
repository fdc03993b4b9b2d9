"""LTL tasks: parsing, translation to a minimal deterministic automaton, labelling and reward."""

from d2spo.ltl.automaton import UNREACHABLE, Automaton, AutomatonArrays, AutomatonTooLarge
from d2spo.ltl.buchi import BuchiAutomaton, NoDeterministicBuchi, to_dba
from d2spo.ltl.parser import parse
from d2spo.ltl.tasks import TASKS, task_formula
from d2spo.ltl.translate import NeverCompletedWarning, translate

__all__ = [
    "TASKS",
    "UNREACHABLE",
    "Automaton",
    "AutomatonArrays",
    "AutomatonTooLarge",
    "BuchiAutomaton",
    "NeverCompletedWarning",
    "NoDeterministicBuchi",
    "parse",
    "task_formula",
    "to_dba",
    "translate",
]
