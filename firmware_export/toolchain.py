"""Compilers for the generated C: the host compiler (a shared library loaded with ctypes, for parity tests and
benchmarks) and ``arm-none-eabi-gcc`` for the Cortex-M4 (an ELF for size and cycle reports)."""
from __future__ import annotations

import ctypes
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_export.mlp_graph import CExportError

WARN_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
"""What the generated policy must compile cleanly with."""
APP_WARN_FLAGS = ("-std=gnu11", "-Wall", "-Wextra", "-Werror")
"""The Crazyflie app's sources, in the firmware's C dialect (gnu11)."""
M4_FLAGS = ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard")
M4_OPT = ("-O2", "-ffast-math")
ARM_GCC = "arm-none-eabi-gcc"
FLASH_BASE = 0x08000000
"""STM32F405 flash and SRAM, as in the Crazyflie 2.x linker script."""
RAM_BASE = 0x20000000
CCM_BASE = 0x10000000
"""The STM32F405's 64 KB core-coupled RAM (data only: the D-bus reaches it, DMA and instruction fetch do not)."""
CCM_BYTES = 64 << 10
M4_LINKER_SCRIPT = f"""ENTRY(swarm_policy_act)
MEMORY {{ FLASH (rx) : ORIGIN = {FLASH_BASE:#x}, LENGTH = 1024K
         RAM (rwx) : ORIGIN = {RAM_BASE:#x}, LENGTH = 128K
         CCMRAM (rw) : ORIGIN = {CCM_BASE:#x}, LENGTH = 64K }}
SECTIONS {{
  .text : {{ *(.text*) }} > FLASH
  .rodata : {{ *(.rodata*) }} > FLASH
  .data : {{ *(.data*) }} > RAM AT > FLASH
  .bss : {{ *(.bss*) *(COMMON) }} > RAM
  .ccmbss (NOLOAD) : {{ *(.ccmbss*) }} > CCMRAM
}}
"""
"""As the Crazyflie's F405 scripts (tools/make/F405/linker): flash, SRAM, and CCM with a NOLOAD ``.ccmbss``."""


class ToolchainError(CExportError):
    """A compiler is missing or rejected the generated code."""


def _run(cmd: list[str], what: str) -> str:
    try:
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    except FileNotFoundError:
        raise ToolchainError(f"{cmd[0]} not found: install it ({what})") from None
    if res.returncode != 0:
        raise ToolchainError(f"{what} failed ({' '.join(cmd)}):\n{res.stderr.strip()}")
    return res.stdout + res.stderr


def host_cc() -> str:
    for cc in ("cc", "gcc", "clang"):
        if shutil.which(cc):
            return cc
    raise ToolchainError("no host C compiler (cc, gcc, clang) on PATH: install gcc")


def build_host_library(c_files: list[Path], out: Path, extra: tuple[str, ...] = ("-O2",),
                       warn: tuple[str, ...] = WARN_FLAGS) -> Path:
    """Compile ``c_files`` into a shared library ``out`` with the project's warning flags.

    Compiling and linking are separate steps on purpose: linking a shared library with ``-ffast-math`` pulls in
    ``crtfastmath.o``, whose constructor turns on flush-to-zero for the whole Python process the moment ctypes
    loads it (numpy and hypothesis then see no subnormals). The objects keep the optimisation; the link does not.
    """
    cc = host_cc()
    objects = []
    for i, src in enumerate(c_files):
        obj = out.with_name(f"{out.stem}.{i}.o")
        _run([cc, *warn, *extra, "-fPIC", "-c", "-o", str(obj), str(src)], "host compile of the generated C")
        objects.append(str(obj))
    _run([cc, "-shared", "-o", str(out), *objects, "-lm"], "host link of the generated C")
    return out


class HostPolicy:
    """``swarm_policy_act`` from a host-compiled library, called through ctypes."""

    def __init__(self, library: Path, obs_dim: int, act_dim: int = 2, init: bool = True) -> None:
        self.lib = ctypes.CDLL(str(library))
        self.fn = self.lib.swarm_policy_act
        fp = ctypes.POINTER(ctypes.c_float)
        self.fn.argtypes = [fp, fp]
        self.fn.restype = None
        self.lib.swarm_policy_init.restype = None
        if init:  # False: as a caller that forgets it (a host build reads the tables in place)
            self.lib.swarm_policy_init()  # tables to their working copy (a no-op with --weights-in flash)
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self._obs = np.zeros(obs_dim, np.float32)
        self._act = np.zeros(act_dim, np.float32)
        self._po = self._obs.ctypes.data_as(fp)
        self._pa = self._act.ctypes.data_as(fp)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """One call; ``obs`` [obs_dim]."""
        self._obs[:] = obs
        self.fn(self._po, self._pa)
        return self._act.copy()

    def act_batch(self, obs: np.ndarray) -> np.ndarray:
        """One call per row of ``obs`` [B, obs_dim]."""
        obs = np.ascontiguousarray(obs, dtype=np.float32)
        out = np.zeros((obs.shape[0], self.act_dim), np.float32)
        fp = ctypes.POINTER(ctypes.c_float)
        for i in range(obs.shape[0]):
            self.fn(obs[i].ctypes.data_as(fp), out[i].ctypes.data_as(fp))
        return out


# --------------------------------------------------------------------------------------------------
# Cortex-M4


def arm_gcc() -> str | None:
    """Path of arm-none-eabi-gcc, or None."""
    return shutil.which(ARM_GCC)


def require_arm_gcc() -> str:
    cc = arm_gcc()
    if cc is None:
        raise ToolchainError(f"{ARM_GCC} not found: install it (Debian/Ubuntu: apt-get install gcc-arm-none-eabi)")
    return cc


def compile_m4_object(c_file: Path, out: Path, include: tuple[Path, ...] = (),
                      opt: tuple[str, ...] = M4_OPT, warn: tuple[str, ...] = WARN_FLAGS) -> Path:
    """One translation unit for the Cortex-M4 with hard float, as the firmware builds it."""
    cmd = [require_arm_gcc(), *warn, *M4_FLAGS, *opt, "-ffunction-sections", "-fdata-sections",
           "-fstack-usage", *[f"-I{p}" for p in include], "-c", "-o", str(out), str(c_file)]
    _run(cmd, "arm-none-eabi-gcc compile for cortex-m4")
    return out


def link_m4_elf(objects: list[Path], out: Path) -> Path:
    """A bare ELF (no startup, no libc) with flash at 0x08000000 and RAM at 0x20000000, for emulation."""
    script = out.with_suffix(".ld")
    script.write_text(M4_LINKER_SCRIPT)
    cmd = [require_arm_gcc(), *M4_FLAGS, "-nostdlib", "-nostartfiles", f"-T{script}", "-Wl,--gc-sections",
           "-Wl,--undefined=swarm_policy_init", "-o", str(out), *map(str, objects), "-lc", "-lgcc"]
    _run(cmd, "arm-none-eabi-gcc link")
    return out


@dataclass(frozen=True)
class SectionSizes:
    text: int
    """Code bytes (flash)."""
    rodata: int
    """Constant tables: weights, biases, scales (flash)."""
    data: int
    """Initialised static RAM (also copied in flash)."""
    bss: int
    """Zeroed static RAM."""
    ccm: int
    """Core-coupled RAM (``.ccmbss``: the weight tables' working copy with ``--weights-in ccm``)."""
    stack: int
    """Stack bytes of ``swarm_policy_act`` (gcc -fstack-usage, kernels inlined or not)."""


def object_sizes(obj: Path) -> SectionSizes:
    """Per-section sizes of a ``compile_m4_object`` output and its stack usage."""
    out = _run([ARM_GCC.replace("gcc", "size"), "-A", str(obj)], "arm-none-eabi-size")
    sizes = {"text": 0, "rodata": 0, "data": 0, "bss": 0, "ccmbss": 0}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            for key in sizes:
                if parts[0] == f".{key}" or parts[0].startswith(f".{key}."):
                    sizes[key] += int(parts[1])
    su = obj.with_suffix(".su")
    stack = 0
    if su.is_file():
        for line in su.read_text().splitlines():
            fields = line.split("\t")
            if len(fields) >= 2 and fields[0].endswith(":swarm_policy_act"):
                stack = int(fields[1])
        # kernels that were not inlined add their own frames on top
        stack += max((int(l.split("\t")[1]) for l in su.read_text().splitlines()
                      if "swp_dense" in l.split("\t")[0]), default=0)
    ccm = sizes.pop("ccmbss")
    return SectionSizes(stack=stack, ccm=ccm, **sizes)
