"""`ocn-finetune`: PPO finetuning of a fresh OCN controller over frozen options on new Craft or Dial tasks.

The RL phase of the paper (section 3.3, appendix A.1): the options of one or more trained `ocn`
checkpoints are pooled (S1: one checkpoint's options; S2: two checkpoints' options concatenated),
a new controller with one initial state per new task is put over the pool, and PPO trains it in
option space (see `lerobot_policy_ocn.tools.rl.ppo`) while every option stays frozen. The result is an ordinary `ocn`
checkpoint with `execution="hard"`, so `load_ocn` and `lerobot-eval --policy.path=DIR/pretrained_model`
run the finetuned hierarchy unchanged. A checkpoint of the MoE or HIL baseline (`hierarchy="moe"` or
`"hil"`) keeps its hierarchy, so its options keep running for their fixed number of steps.

The new controller's softmax temperature is 1 (`FRESH_CONTROLLER_TEMPERATURE`), not the
imitation phase's T = 10: the paper gives T only for imitation, where it slows the controller
against the options ("fast and slow learning"), and its PPO table has none. A fresh controller at
T = 10 starts with near-uniform choices that PPO's learning rate moves ten times more slowly; on
S1 over the same frozen options, T = 1 reached 0.59 sparse success on ADC in 200k frames in two
seeds against 0.33 and 0.46 at T = 10 (`results/archive/baselines_s1_adc`).

The world PPO acts in is the checkpoints' own, read from the widths of their state and action
(`lerobot_policy_ocn.tools.worlds.policy_world`: 81 floats and one action index for Craft, 39 floats and 9 motor
controls for Dial), since a checkpoint has no dataset beside it to ask; the PPO loop, its semi-MDP
GAE and this command are the same code for both, the world entering only through its batch
simulator, its task names and how actions reach the env (`lerobot_policy_ocn.tools.rl.ppo.Acting`). States and actions
go through the first checkpoint's pre- and post-processors, as under `lerobot-eval`: on Dial they
standardise the 39 floats and unstandardise the 9 torques with the dataset's statistics (so pooled
Dial checkpoints must share them), on Craft they are identities. The finetuned checkpoint is saved
with those processors, so `lerobot-eval --env.type=dial --env.task=124` runs it as it trained.

Tasks are a fixed comma-separated list (Craft `ADC,CAD,DCA`, Dial PINs `124,481,842`), not PINs
drawn afresh each episode: the controller learns one initial state h^c_{tau,0} per task, and on
Dial that state is the only place the PIN reaches the policy (the 39 floats hold the arm and the
key offsets, not the PIN), so each PIN the controller must dial is a task of its own. The paper's
Dial finetuning dials 3-digit PINs from S = (1, 2, 4, 8); a list of all of them (36) is one
`--tasks` away.

A `compile` checkpoint gets compILE's RL form (the paper's: decoder frozen, a re-initialised encoder
predicting the latent, trained by the same PPO). With concrete latents, the frozen decoder given the
one-hot latent k is a one-step option, so the decoder is a pool of `latent_dim` options
(`lerobot_policy_ocn.ocn.latent_options`); the fresh controller chooses one at every step (`hierarchy="moe"`,
temperature 1 unless --temperature says otherwise), exactly as --flat chooses primitive actions.
The result is an `ocn` checkpoint whose options are that decoder (`decoder_latents` > 0), so
`lerobot-eval` and the tools run it like any other. Several compile checkpoints (S2) stack their
decoders into one pool, option d * latent_dim + k being decoder d given latent k. A compILE with
Gaussian latents has no pool of latents to choose from and is refused.

An `ompn` checkpoint gets OMPN's RL form (`lerobot_policy_ocn.tools.rl.ompn_rl`): OMPN cannot be split into options, so
the whole network, with one new task embedding per new task, is finetuned by the same PPO on
primitive actions, and the result is an `ompn` checkpoint. Only one, in Craft: it pools with nothing.

`--flat` (instead of --checkpoint) trains Craft's flat PPO baseline from scratch, with no demos: a
policy on primitive actions, built as the same network whose N = 5 options are the five primitive
actions as frozen one-step options (option a always emits action a) under `hierarchy="moe"`, so the
controller picks an action at every step. The controller is then an ordinary recurrent actor (the
OCN cell over the Craft observation features, one learned initial state per task, temperature 1
unless --temperature says otherwise) and trains by the very same PPO code; its curves are
comparable with OCN's on env frames, and its checkpoint runs under `lerobot-eval` like any other.
Dial has no primitive-action pool (its actions are 9 continuous torques) and the paper's Dial
comparison (figure 6) has no flat baseline, so `--flat` with Dial PINs is refused.

Writes into --out: curve.csv (one row per PPO iteration: env frames, mean return, success overall
and per task as `success[ADC]` or `success[124]`, PPO statistics), curve.png, finetune.json
(settings and summary), pretrained_model/ (config, weights and the first checkpoint's
pre/post-processors) and training_state.pt, rewritten after every iteration (`tools.rl.ppo.RunSnapshot`):
`--resume` with the same command goes on from it after an interruption, as if the run had not stopped.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lerobot_policy_ocn.tools.rl.finetune_settings import STATE_FILE, PPOConfig


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ocn-finetune", description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, action="append", default=[],
                        help="a pretrained_model folder of an ocn or compile checkpoint (repeat to pool several "
                             "option sets), or of one ompn checkpoint")
    parser.add_argument("--flat", action="store_true",
                        help="no checkpoint: flat PPO from scratch over Craft's primitive actions (the baseline; "
                             "not on Dial)")
    parser.add_argument("--hidden-size", type=int, default=128,
                        help="with --flat: width of the recurrent actor's state and MLP")
    parser.add_argument("--tasks", required=True,
                        help="comma-separated new tasks: Craft subtask letters (e.g. ADC,CAD,DCA) or named tasks; "
                             "Dial PINs (e.g. 124,481,842)")
    parser.add_argument("--reward", choices=("sparse", "dense"), default="sparse")
    parser.add_argument("--frames", type=int, default=500_000, help="env frames to train for")
    parser.add_argument("--envs", type=int, default=64, help="envs stepped together; one episode each per iteration")
    parser.add_argument("--seed", type=int, default=0,
                        help="seeds the new controller, the sampling and the envs (Craft maps, Dial start poses)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (must be new or empty)")
    parser.add_argument("--resume", action="store_true",
                        help=f"go on with the interrupted run in --out from its {STATE_FILE}, under the same settings")
    parser.add_argument("--mode", choices=("paper", "full"), default="paper", help="Craft world mode (Dial has none)")
    parser.add_argument("--max-steps", type=int, default=None,
                        help="episode step limit (default: the env's; Craft 100 for tasks of 3+ subtasks, Dial 150 "
                             "per digit)")
    parser.add_argument("--temperature", type=float, default=None,
                        help="the new controller's softmax temperature T (default 1: the imitation phase's T = 10 "
                             "keeps a fresh controller's choices near uniform at PPO's learning rate, see "
                             "results/archive/baselines_s1_adc)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads; the per-step matmuls are small, and more threads than free "
                             "cores slow them down many times over")
    ppo = parser.add_argument_group("PPO (defaults from the paper's appendix A.2)")
    paper = PPOConfig()
    ppo.add_argument("--lr", type=float, default=paper.lr, help="initial Adam lr, decayed linearly to 0")
    ppo.add_argument("--epochs", type=int, default=paper.epochs)
    ppo.add_argument("--batch-size", type=int, default=paper.batch_size, help="controller decisions per minibatch")
    ppo.add_argument("--gamma", type=float, default=paper.gamma)
    ppo.add_argument("--gae-lambda", type=float, default=paper.gae_lambda)
    ppo.add_argument("--clip", type=float, default=paper.clip)
    ppo.add_argument("--entropy", type=float, default=paper.entropy_coef, help="entropy bonus coefficient")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    from lerobot_policy_ocn.tools.rl.finetuning import finetune_checkpoints

    try:
        summary = finetune_checkpoints(args)
    except (FileNotFoundError, FileExistsError, ValueError) as error:
        print(f"ocn-finetune: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # a full disk mid-run: the last snapshot stays (it is replaced atomically)
        print(f"ocn-finetune: cannot write {error.filename or args.out} ({error.strerror or error}); free space, then "
              f"go on with --resume if {args.out / STATE_FILE} exists (else run again)", file=sys.stderr)
        return 1
    print(
        f"{summary['frames']} frames in {summary['wall_s']} s ({summary['frames_per_s']} frames/s); last iteration: "
        f"success {summary['final_success']:.3f}, mean return {summary['final_mean_return']:.3f}"
    )
    print(f"wrote {args.out}/curve.csv, curve.png, finetune.json and pretrained_model/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
