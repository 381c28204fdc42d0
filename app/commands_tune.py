"""The `tune` command and the lab's learner options: hyperparameter search (the paper's Algorithm 1 or Bayesian)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from app.common import emit, load_cell_config
from cell.cliargs import COUNT, NTHREAD, int_in
from cell.model.dynamics.learned import LEARNERS
from drivers.errors import ConfigError


def learner_list(text: str) -> list[str]:
    """'dnn,lstm' -> ['dnn', 'lstm'], each one of LEARNERS."""
    names = [t.strip() for t in text.split(",") if t.strip()]
    bad = [n for n in names if n not in LEARNERS]
    if bad or not names:
        raise argparse.ArgumentTypeError(f"{text!r}: learners are a comma-separated subset of {', '.join(LEARNERS)}")
    return names


def add_learner_parsers(sub: argparse._SubParsersAction, common: Callable[[argparse.ArgumentParser], None],
                        robot_option: Callable[..., None], train: argparse.ArgumentParser,
                        evaluate: argparse.ArgumentParser) -> None:
    """`--learner` on train, `--learners`/`--tuned` on evaluate, and the `tune` command (kept here so
    main.py stays a short dispatcher)."""
    train.add_argument("--learner", choices=LEARNERS, default="xgboost",
                       help="the learned part of D/H1/H2/H3: xgboost (default), dnn or lstm (JAX, CPU)")
    evaluate.add_argument("--learners", type=learner_list, default=None, metavar="L1,L2",
                          help="also fit D, H1, H2, H3 with these learners (dnn,lstm): rows D_dnn, H1_lstm, ...")
    evaluate.add_argument("--tuned", nargs="+", default=None, metavar="DIR",
                          help="`tune` output folders: their best settings refitted here (row <model>_<learner>_tuned)")
    evaluate.add_argument("--max-epochs", type=COUNT, default=None, help="cap on the networks' epochs (quick runs)")
    tu = sub.add_parser("tune", help="search a learned model's hyperparameters (grid: Algorithm 1; bayes: Optuna)")
    tu.add_argument("--data", required=True, help="dataset manifest (dataset.yaml); only its training split is read")
    tu.add_argument("--model", choices=("D", "H1", "H2", "H3"), default="H1", help="the model tuned (its learned part)")
    tu.add_argument("--learner", choices=LEARNERS, default="xgboost", help="the learned part: trees, DNN or LSTM")
    tu.add_argument("--method", choices=("grid", "bayes"), default="bayes",
                    help="grid: the paper's Algorithm 1 over the space; bayes: Optuna")
    tu.add_argument("--trials", type=COUNT, default=40, help="configurations to evaluate (over all workers and runs)")
    tu.add_argument("--workers", type=int_in(1, 64), default=1, help="worker processes sharing the study")
    tu.add_argument("--storage", default=None,
                    help="Optuna storage: a journal file path or a database URL (default <out>/study.journal)")
    tu.add_argument("--space", default=None, help="search space YAML (default config/tune/<learner>.yaml)")
    tu.add_argument("--samples", type=int_in(100), default=24_000, help="training samples (whole moves)")
    tu.add_argument("--sampler", choices=("tpe", "gp"), default="tpe", help="bayes: Optuna's sampler")
    tu.add_argument("--max-epochs", type=COUNT, default=None, help="cap on the networks' epochs (quick runs)")
    tu.add_argument("--nthread", type=NTHREAD, default=1, help="threads per worker")
    tu.add_argument("--out", required=True, help="output folder (model/, history.json, history.png, study)")
    robot_option(tu, "the dataset's ")
    common(tu)
    tu.set_defaults(func=cmd_tune)


def check_storage_url(url: str) -> None:
    """Open the database storage once before the search: a missing database driver or a bad URL is one line
    here, not a traceback in every worker."""
    from tasks.lab.tune import storage_for

    try:
        storage_for(Path("."), url)
    except ImportError as exc:
        raise ConfigError(f"--storage {url}: needs the Python package {exc.name or 'for this database'!r}, "
                          "which is not installed (or use a journal file path)") from None
    except Exception as exc:  # SQLAlchemy's and the drivers' errors: no common base to name here
        first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise ConfigError(f"--storage {url}: cannot open the database ({first})") from None


def cmd_tune(args: argparse.Namespace) -> int:
    from tasks.lab.tune import tune

    if args.storage and "://" not in args.storage and Path(args.storage).is_dir():
        raise ConfigError(f"--storage {args.storage}: a folder; give a journal file path or a database URL")
    if args.storage and "://" in args.storage:
        check_storage_url(args.storage)
    out = tune(load_cell_config(args), Path(args.data), Path(args.out), kind=args.model, learner=args.learner,
               method=args.method, trials=args.trials, workers=args.workers, storage=args.storage,
               space_path=Path(args.space) if args.space else None, samples=args.samples, sampler=args.sampler,
               nthread=args.nthread, seed=args.seed or 0, robot=args.robot, max_epochs=args.max_epochs)
    emit(out, args.json)
    return 0
