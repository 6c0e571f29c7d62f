"""The control loop's schedule from a command's flags (``dssp-run``, ``dssp-sim eval``), built once into a
:mod:`dssp_deploy.schedules` config; what the configs refuse is the command's one ``error:`` line, in its flags."""

from __future__ import annotations

from dssp_core.errors import ConfigError
from dssp_deploy.schedules import MODES, SettingError, config_for

FLAGS = {"smoothing": "--smoothing", "prefetch": "--prefetch", "every": "--ensemble-every", "decay": "--ensemble-decay"}


def add_schedule_arguments(parser, also: str = "") -> None:
    """``--smoothing``, ``--ensemble-every``, ``--ensemble-decay``: the loop's schedule; ``also``: a note for --smoothing."""
    parser.add_argument(
        "--smoothing",
        choices=list(MODES),
        default="none",
        help="none (default): each tick's action from the current chunk, a new one every H_a ticks; "
        "ensemble: a chunk every --ensemble-every ticks and the weighted mean of every kept chunk's "
        "prediction for the tick (ACT's temporal ensembling; H_a / N times the denoiser work"
        + (f"; {also}" if also else "")
        + "); rtc: real-time chunking, the next chunk "
        "computed while the current one executes and inpainted to agree with it (a model exported "
        "with --inpainting)",
    )
    parser.add_argument(
        "--ensemble-every",
        type=int,
        metavar="N",
        help="--smoothing ensemble: ticks between chunks, 1 to the model's H_a (default 1: every tick)",
    )
    parser.add_argument(
        "--ensemble-decay",
        type=float,
        metavar="M",
        help="--smoothing ensemble: the i-th oldest prediction for a tick weighs exp(-M i) (default 0.01: "
        "the older weigh more, as in ACT; 0: the plain mean)",
    )


def schedule_of(args):
    """The schedule config the flags ask for (as far as it can be judged without the model); one line otherwise."""
    try:
        return config_for(
            args.smoothing,
            prefetch=getattr(args, "prefetch", False) or None,
            every=args.ensemble_every,
            decay=args.ensemble_decay,
        )
    except SettingError as exc:
        raise refusal(exc, "") from None


def refusal(exc: ValueError, what: str) -> ConfigError:
    """A schedule's refusal as the command's one line: a setting's in the flags' names, anything else after ``what``."""
    return ConfigError(exc.named(FLAGS) if isinstance(exc, SettingError) else f"{what}: {exc}")


def model_flags_given(args, *also: tuple[str, bool]) -> list[str]:
    """The model-only flags ``args`` sets (``add_runtime_arguments``', ours, then ``also``: a command's, (flag, given))."""
    flags = (
        ("--precision", args.precision is not None),
        ("--kernel", args.kernel != "auto"),
        ("--no-spin", args.no_spin),
        ("--smoothing", args.smoothing != "none"),
        ("--ensemble-every", args.ensemble_every is not None),
        ("--ensemble-decay", args.ensemble_decay is not None),
        *also,
    )
    return [flag for flag, given in flags if given]
