"""Run an Anipose project unchanged: read its ``config.toml`` and folders as Anipose does, solve
every trial with acinoset, and write where ``anipose triangulate`` writes.

    from graph.anipose import load_project, run_project
    project = load_project("~/my-anipose-project")     # trials, options, keys ignored
    outcomes = run_project(project, jobs=2)              # solved / skipped / failed per trial

:mod:`.project` reads the project (config, sessions, calibrations, trials); :mod:`.batch` solves
trials in parallel processes and skips those already done; :mod:`.cli` is ``acinoset anipose``.
"""

from graph.anipose.batch import TrialEvent, TrialOutcome, run_project, solve_trial, up_to_date
from graph.anipose.project import Project, Trial, load_project

__all__ = ["Project", "Trial", "TrialEvent", "TrialOutcome", "load_project", "run_project", "solve_trial",
           "up_to_date"]
