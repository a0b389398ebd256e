"""The memory the stock Crazyflie firmware leaves to the app, measured on a real firmware build, and the check
that an export's tables fit it.

Measured with ``firmware_export/check_in_firmware.sh`` (results/c_export_report.md, "In the real firmware"):
bitcraze/crazyflie-firmware at ``FIRMWARE_COMMIT`` with its pinned submodules, ``make cf2_defconfig && make``,
arm-none-eabi-gcc 12.2.1. The regions and the way usage is counted are the firmware's own
(``tools/make/size.py``: flash = .text + .data + .ccmdata of 1008 KB (the bootloader keeps the first 16 KB),
RAM = .bss + .data of 128 KB, CCM = .ccmbss + .ccmdata of 64 KB).

The app shell (``swarm_app.c``, ``swarm_logic.c``, the app task and its 500-word stack) adds ``APP_SHELL`` to each
region; the policy adds its code to flash and its tables to flash plus, with ``ram`` or ``ccm``, a working copy
there. ``check`` refuses a placement whose total goes over a region and names the fix.
"""
from __future__ import annotations

import argparse
import subprocess
from dataclasses import dataclass
from pathlib import Path

from firmware_export.mlp_graph import CExportError

FIRMWARE = "bitcraze/crazyflie-firmware"
FIRMWARE_COMMIT = "2a18fc299d7b48cf094d26c38a79f33dec64b5d7"
FIRMWARE_CONFIG = "cf2_defconfig"
FIRMWARE_TOOLCHAIN = "arm-none-eabi-gcc 12.2.1 (Debian 15:12.2.rel1-1)"


@dataclass(frozen=True)
class Usage:
    """Bytes of flash, RAM and CCM, counted as the firmware's ``tools/make/size.py`` counts them."""

    flash: int
    ram: int
    ccm: int

    def __add__(self, other: "Usage") -> "Usage":
        return Usage(self.flash + other.flash, self.ram + other.ram, self.ccm + other.ccm)

    def __sub__(self, other: "Usage") -> "Usage":
        return Usage(self.flash - other.flash, self.ram - other.ram, self.ccm - other.ccm)


CAPACITY = Usage(flash=1008 * 1024, ram=128 * 1024, ccm=64 * 1024)
"""The firmware's MEM_SIZE_FLASH_K / MEM_SIZE_RAM_K / MEM_SIZE_CCM_K (its top-level Makefile)."""
STOCK = Usage(flash=306_708, ram=93_184, ccm=64_888)
"""The stock cf2 firmware (no app) at FIRMWARE_COMMIT."""
APP_SHELL = Usage(flash=3_676, ram=3_216, ccm=96)
"""The app without its policy: with-app build minus STOCK minus the policy object (measured, see the report)."""
POLICY_CODE_MAX = 2048
"""Upper bound of the policy's code (measured 0.9-1.4 KB for the 64-64 actors in every placement)."""
MEASURED_BUILDS = {
    "app, float, ram (default)": ("float", "ram", 28_936, 884),
    "app, float, flash": ("float", "flash", 28_936, 868),
    "app, int8w, ram": ("int8w", "ram", 8_712, 1_328),
    "app, int8w, flash": ("int8w", "flash", 8_712, 1_316),
}
"""The builds with the app recorded in the report (row label -> quant, placement, table bytes, policy code bytes:
the 45-64-64-2 pursuer, ``policy.o``'s ``.text``); ``predicted`` reproduces their usage (tests/test_fw_budget.py)."""
ALIGN_SLACK = 16
"""Bytes the linker's section alignment may add to flash around the policy's tables."""


def policy_usage(table_bytes: int, weights_in: str, code_bytes: int = POLICY_CODE_MAX) -> Usage:
    """What one policy adds: code and tables in flash, and the tables' working copy in RAM or CCM."""
    return Usage(flash=code_bytes + table_bytes, ram=table_bytes if weights_in == "ram" else 0,
                 ccm=table_bytes if weights_in == "ccm" else 0)


def predicted(table_bytes: int, weights_in: str, code_bytes: int = POLICY_CODE_MAX) -> Usage:
    """The firmware's usage with the app in."""
    return STOCK + APP_SHELL + policy_usage(table_bytes, weights_in, code_bytes)


def check(table_bytes: int, weights_in: str, what: str = "the policy") -> Usage:
    """Raise ``CExportError`` naming the fix when the placement does not fit the stock firmware; else the
    predicted usage."""
    need = predicted(table_bytes, weights_in)
    for region in ("ram", "ccm", "flash"):
        used, cap = getattr(need, region), getattr(CAPACITY, region)
        if used > cap:
            free = cap - getattr(STOCK + APP_SHELL, region)
            fix = {"ccm": "use --weights-in ram (the default: main SRAM, also zero wait states) or flash",
                   "ram": "use --quant int8w (3.3x smaller tables) or --weights-in flash",
                   "flash": "use --quant int8w"}[region]
            raise CExportError(
                f"--weights-in {weights_in}: {what}'s {table_bytes} B of tables do not fit: the stock Crazyflie "
                f"firmware ({FIRMWARE} {FIRMWARE_COMMIT[:8]}, {FIRMWARE_CONFIG}) with the app leaves {free} B of "
                f"{region.upper()}, it needs {used - cap + free} B; {fix} (or --ignore-budget for a firmware built "
                "with more free memory)")
    return need


def elf_usage(elf: Path, size_tool: str = "arm-none-eabi-size") -> Usage:
    """Usage of a linked firmware ELF, the firmware's way (``tools/make/size.py``)."""
    out = subprocess.run([size_tool, "-A", str(elf)], check=True, capture_output=True, text=True).stdout
    sizes: dict[str, int] = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    s = lambda name: sizes.get(name, 0)  # noqa: E731
    return Usage(flash=s(".text") + s(".data") + s(".ccmdata"), ram=s(".bss") + s(".data"),
                 ccm=s(".ccmbss") + s(".ccmdata"))


def format_usage(u: Usage) -> str:
    rows = []
    for region in ("flash", "ram", "ccm"):
        used, cap = getattr(u, region), getattr(CAPACITY, region)
        rows.append(f"{region.upper():5s} {used:7d} / {cap:7d} B ({100 * used / cap:4.1f} %), {cap - used:7d} free "
                    f"(stock firmware: {getattr(STOCK, region)})")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="flash, RAM and CCM use of a Crazyflie firmware ELF, against the "
                                            "stock firmware's (" + FIRMWARE_COMMIT[:8] + ")")
    p.add_argument("elf", type=Path, help="the firmware ELF, e.g. APP/build/cf2.elf")
    args = p.parse_args(argv)
    print(format_usage(elf_usage(args.elf)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
