"""RL Zoo's experiment manager for HhP, which ``python -m sb3_hhp.train`` hands to :func:`rl_zoo3.train.train`.

It differs from RL Zoo's :class:`~rl_zoo3.exp_manager.ExperimentManager` where HhP needs it: the hyperparameters
come from the env id's entry or its domain's (:func:`~sb3_hhp.zoo.config.select_entry`) and are checked before
anything is built; ``--oracle`` and a durable preference database in the run folder join them; ``--checkpoint-freq``
adds the latest-checkpoint callback and ``--resume`` loads the model and its replays from a checkpoint; the labeling
server runs beside training with ``--label-server``; and the trained model and training time are kept for the
evaluation that follows.
"""

import argparse
import functools
import json
import os
import time
from collections import OrderedDict
from pprint import pprint
from typing import Any

import yaml

from sb3_hhp.zoo.checkpoints import RESUMED_FILE, answers_database, checkpoint_callback_class, read_checkpoint, resume_seed
from sb3_hhp.zoo.config import PREFERENCE_DB_NAME, ZOO_KEYS, ConfigError, select_entry, validate_hyperparams


def experiment_manager_class() -> type:
    """``HhPExperimentManager``, a subclass of RL Zoo's experiment manager (built on first use, so that importing this
    module does not import RL Zoo and optuna)."""
    from rl_zoo3.exp_manager import ExperimentManager

    class HhPExperimentManager(ExperimentManager):
        """RL Zoo's experiment manager for HhP: domain entries, key checks, the oracle and preference
        database, callbacks in primitive steps, the labeling server; it keeps the trained model."""

        def __init__(self, *args: Any, hhp_options: argparse.Namespace, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self.hhp_options = hhp_options
            self.trained_model: Any = None
            self.train_seconds = 0.0
            self.label_server: Any = None
            self.config_entry = ""
            self.checkpoint = read_checkpoint(hhp_options.resume) if hhp_options.resume else None
            self.start_timesteps = 0
            if self.checkpoint is not None:  # RL Zoo's own way of going on from a saved model, by its name
                self.trained_agent, self.continue_training = self.checkpoint["model"], True

        def read_hyperparameters(self) -> tuple[dict[str, Any], dict[str, Any]]:
            if not self.config.endswith((".yml", ".yaml")):  # a .py file or a module: RL Zoo reads it
                hyperparams, _ = super().read_hyperparameters()
                self.config_entry = self.env_name.gym_id
            else:
                print(f"Loading hyperparameters from: {self.config}")
                try:
                    with open(self.config) as file:
                        table = yaml.safe_load(file)
                except OSError as error:
                    raise ConfigError(f"Cannot read the hyperparameter file {self.config}: {error}") from error
                self.config_entry = select_entry(table, self.env_name.gym_id, self.config)
                if self.config_entry != self.env_name.gym_id:
                    print(f"Using the {self.config_entry!r} entry for {self.env_name.gym_id}")
                hyperparams = dict(table[self.config_entry] or {})
                # as RL Zoo's own read_hyperparameters from here on
                if self.storage and self.study_name and self.trial_id:
                    print("Loading from Optuna study...")
                    hyperparams.update(self.load_trial(self.storage, self.study_name, self.trial_id))
                if self.custom_hyperparams is not None:
                    validate_hyperparams(dict(self.custom_hyperparams), "--hyperparams")
                    hyperparams.update(self.custom_hyperparams)
                if "env_kwargs" in hyperparams and self.env_kwargs:
                    hyperparams.update({"env_kwargs": self.env_kwargs})
                    if self._eval_env_kwargs_args is None:
                        self.eval_env_kwargs = hyperparams["env_kwargs"]
            options = self.hhp_options
            if options.oracle is not None:
                hyperparams["oracle"] = options.oracle
            # every run keeps its answers in a durable store; optuna trials would share one, so they get none
            if "preference_db" not in hyperparams and not (self.optimize_hyperparameters and not options.label_server):
                # a resumed run goes on with the answers of the run it resumes
                hyperparams["preference_db"] = (answers_database(self.checkpoint["run_folder"]) if self.checkpoint
                                                is not None else os.path.join(self.save_path, PREFERENCE_DB_NAME))
            validate_hyperparams(hyperparams, f"{self.config} [{self.config_entry}]")
            self._check_values(hyperparams)
            if self.n_timesteps > 0:  # -n overrides the file: the dump (config.yml) says what was trained
                hyperparams["n_timesteps"] = self.n_timesteps
            saved_hyperparams = OrderedDict([(key, hyperparams[key]) for key in sorted(hyperparams.keys())])
            print("Default hyperparameters for environment (ones being tuned will be overridden):")
            pprint(saved_hyperparams)
            return hyperparams, saved_hyperparams

        def _check_values(self, hyperparams: dict[str, Any]) -> None:
            """HhP's checks of the values, before anything is created, blaming ``--hyperparams`` or the file."""
            from sb3_hhp import HhP

            def check(values: dict[str, Any]) -> None:
                kwargs = {key: value for key, value in values.items() if key not in ZOO_KEYS}
                HhP(values.get("policy", "MlpPolicy"), None, _init_setup_model=False, **kwargs)

            custom = dict(self.custom_hyperparams or {})
            try:
                check(hyperparams)
            except (ValueError, TypeError) as error:
                from_file = {key: value for key, value in hyperparams.items() if key not in custom}
                try:
                    check(from_file)
                except (ValueError, TypeError):
                    raise ConfigError(f"{self.config} [{self.config_entry}]: {error}") from error
                raise ConfigError(f"--hyperparams: {error}") from error

        def setup_experiment(self) -> Any:
            try:
                results = super().setup_experiment()
            except ConfigError:
                raise
            except (ValueError, TypeError) as error:  # HhP's constructor refusing a value from the file
                raise ConfigError(f"{self.config} [{self.config_entry}]: {error}") from error
            if results is not None and self.hhp_options.label_server:
                from sb3_hhp.label.server import LabelServer

                model = results[0]
                self.label_server = LabelServer(model.store, host="127.0.0.1", port=self.hhp_options.label_port).start()
                print(f"Labeling page: {self.label_server.url} (answers go to {model.store.path})", flush=True)
            return results

        def create_callbacks(self) -> None:
            super().create_callbacks()
            if self.hhp_options.checkpoint_freq > 0:
                earlier = self.checkpoint["train_seconds"] if self.checkpoint is not None else 0.0
                self.callbacks.append(checkpoint_callback_class()(self.hhp_options.checkpoint_freq, self.save_path, earlier))

        def _load_pretrained_agent(self, hyperparams: dict[str, Any], env: Any) -> Any:
            """The checkpoint of ``--resume``: the model as it was saved (its own hyperparameters), with this run's
            oracle and preference database, and its replays."""
            from sb3_hhp import HhP

            checkpoint = self.checkpoint
            print(f"Resuming {checkpoint['run_folder']} at {checkpoint['timesteps']} steps")
            os.makedirs(self.save_path, exist_ok=True)  # where this part's evaluations begin (benchmarks join the parts)
            part_seed = resume_seed(self.seed, int(checkpoint["timesteps"]))
            with open(os.path.join(self.save_path, RESUMED_FILE), "w") as file:
                json.dump({"run_folder": checkpoint["run_folder"], "timesteps": checkpoint["timesteps"],
                           "seed": part_seed}, file)
            chosen = {key: hyperparams[key] for key in ("oracle", "preference_db") if hyperparams.get(key) is not None}
            model = HhP.load(checkpoint["model"], env=env, seed=self.seed, device=self.device, verbose=self.verbose,
                             tensorboard_log=self.tensorboard_log, **chosen)  # else the ones it was saved with
            model.load_replay_buffer(checkpoint["replay"])
            model.set_random_seed(part_seed)  # the envs' next layouts, exploration and torch: not the run's first ones
            return model

        def learn(self, model: Any) -> None:
            start = time.perf_counter()
            self.start_timesteps = int(model.num_timesteps)
            if self.checkpoint is None:
                super().learn(model)
            else:  # -n is the run's whole budget: train what is left, the step count going on
                budget = self.n_timesteps
                self.n_timesteps = max(0, budget - model.num_timesteps)
                model.learn = functools.partial(type(model).learn, model, reset_num_timesteps=False)
                try:
                    if self.n_timesteps > 0:
                        super().learn(model)
                    else:
                        print(f"The checkpoint is at {model.num_timesteps} steps, the budget (-n) {budget}: nothing to train")
                finally:
                    del model.learn
                    self.n_timesteps = budget
            self.train_seconds = time.perf_counter() - start

        def save_trained_model(self, model: Any) -> None:
            super().save_trained_model(model)
            self.trained_model = model

    return HhPExperimentManager
