"""What `romannet info` reports: versions, per-net parameter counts, threads and the resolved config."""

from __future__ import annotations

import platform
from importlib import metadata
from typing import Any

from romannet.common.config import Config
from romannet.common.configbase import dumps_toml, to_dict


def _version(dist: str) -> str:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo ("" where unreadable), for benchmark and eval reports."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def collect_info(cfg: Config) -> dict[str, Any]:
    import torch

    from romannet.common.model import RoManNet, parameter_count

    model = RoManNet(cfg.model)
    return {
        "romannet": _version("romannet"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "versions": {d: _version(d) for d in ("torch", "numpy", "eclipse-zenoh", "pybullet", "mcap", "protobuf")},
        "torch_threads": torch.get_num_threads(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "heightmap_px": [cfg.workspace.height_px, cfg.workspace.width_px],
        "parameters_per_net": {name: parameter_count(net) for name, net in model.nets.items()},
        "config": to_dict(cfg),
    }


def format_info(info: dict[str, Any]) -> str:
    from romannet.common.config import Config
    from romannet.common.configbase import from_dict

    lines = [
        f"romannet {info['romannet']}  (python {info['python']}, {info['platform']})",
        "versions: " + ", ".join(f"{k} {v}" for k, v in info["versions"].items()),
        f"torch threads: {info['torch_threads']}  cpu capability: {info['torch_cpu_capability']}",
        f"heightmap: {info['heightmap_px'][0]}x{info['heightmap_px'][1]} px",
        "parameters per net: " + ", ".join(f"{k} {v:,}" for k, v in info["parameters_per_net"].items()),
        "",
        "# resolved config",
        dumps_toml(from_dict(Config, info["config"])),
    ]
    return "\n".join(lines)
