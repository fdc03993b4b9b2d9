"""LTL tasks: parsing, translation to a minimal deterministic automaton, labelling and reward."""

from d2spo.ltl.automaton import UNREACHABLE, Automaton, AutomatonArrays, AutomatonTooLarge
from d2spo.ltl.buchi import BuchiAutomaton, NoDeterministicBuchi, to_dba
from d2spo.ltl.buchi_task import BuchiTask, task_automaton
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
    "BuchiTask",
    "NeverCompletedWarning",
    "NoDeterministicBuchi",
    "parse",
    "task_automaton",
    "task_formula",
    "to_dba",
    "translate",
]
