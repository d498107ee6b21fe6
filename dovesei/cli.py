"""The user-facing `dovesei` command: one subcommand per job, each in its own module.

Subcommands are imported only when chosen, so `dovesei up --help` never loads torch and the
onboard image (no torch) can run everything but the CLIPSeg backend. A project error that a
command lets escape becomes one line on stderr (exit 2 for a bad configuration, 1 otherwise):
a user never sees a traceback for something the project raised on purpose.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import sys

from dovesei.shared.errors import ConfigError, DoveseiError

# name -> (module, help). Each module has main(argv) -> int.
COMMANDS: dict[str, tuple[str, str]] = {
    "smoke": ("dovesei.smoke", "check the install: codec round trip and a loopback Zenoh session"),
    "up": ("dovesei.up", "fly one simulated (or real) landing with the three services as separate processes"),
    "bench": ("dovesei.bench", "the paper's experiment: N starts x policies, judged, resumable"),
    "sweep": ("dovesei.sweep", "a grid of policies x perception profiles x worlds x prompt sets, one table and plot"),
    "calibrate": ("dovesei.calibrate", "success rates vs simulated perception noise, both timing presets"),
    "bench-sim": ("dovesei.benchmarks.sim", "simulator speed: render fps and lockstep real-time factor"),
    "bench-segmenter": ("dovesei.benchmarks.segmenter", "CLIPSeg reference vs fast path, and the simulated backend"),
    "bench-policy": ("dovesei.benchmarks.policy", "policy compute time per heatmap at 352x352"),
    "bench-closelook": ("dovesei.benchmarks.closelook", "close look: sim crop render ms, crop -> CLIPSeg -> verdict s"),
    "closelook-stats": ("dovesei.benchmarks.closelook_stats", "the close look's rule on simulated crops: people missed, clear ground fired on"),
    "bench-loop": ("dovesei.benchmarks.loop", "controller loop jitter at 20 Hz with a 2 Hz segmenter"),
    "perception-stats": ("dovesei.perception_stats", "simulated perception vs real CLIPSeg statistics (threshold, precision)"),
    "preview": ("dovesei.preview", "PNG pictures of a world, the camera's view and the simulated perception"),
    "health": ("dovesei.health", "exit 0 when a service's liveliness token is visible"),
    "faults": ("dovesei.faults", "the fault suite: hangs, kills, a router restart, message loss, skew, floods, forgeries"),
    "certs": ("dovesei.certs", "a CA, one certificate per role and the router's ACL for the secured Zenoh mode"),
    "policy-config": ("dovesei.policy_config", "a policy's constants as a TOML file for --policy-config, or check one"),
    "replay": ("dovesei.replay", "run a policy (and optionally a segmenter) again on a flight recording (.mcap)"),
    "view": ("dovesei.view", "open a flight (report folder or recording.mcap) in Rerun; writes an .rrd"),
    "bench-codec": ("dovesei.benchmarks.codec", "encode/decode time of a 352x352 frame and heatmap"),
    "bench-odometry": ("dovesei.benchmarks.odometry", "visual velocity: ms per 640x480 frame, error vs truth on the suite"),
}


def version() -> str:
    """The installed distribution's version (pyproject's), which is what a bug report should name."""
    try:
        return importlib.metadata.version("dovesei")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in ("-V", "--version"):
        print(f"dovesei {version()}")
        return 0
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: dovesei [--version] <command> [options]  (dovesei <command> --help for its options)"
              "\n\ncommands:")
        for name, (_, text) in COMMANDS.items():
            print(f"  {name:<18} {text}")
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"dovesei: unknown command {name!r}; choose one of {', '.join(COMMANDS)} (see dovesei --help)",
              file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    try:
        return int(module.main(rest) or 0)
    except ConfigError as exc:  # a bad flag or file a command did not catch itself: still one line
        print(f"dovesei {name}: {exc}", file=sys.stderr)
        return 2
    except DoveseiError as exc:  # an expected failure (a world, a link, a model): one line, no traceback
        print(f"dovesei {name}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"dovesei {name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
