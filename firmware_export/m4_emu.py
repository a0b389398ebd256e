"""Run the Cortex-M4 build of ``swarm_policy_act`` in an emulator (unicorn, Cortex-M4 model) and estimate
its cycles.

Instructions are counted as executed (a unicorn code hook records every address). Cycles come from the
Cortex-M4 Technical Reference Manual's timing tables (ARM DDI 0439, Table 3-1 for the integer core, Table 7-1
for the FPU), applied to each executed instruction:

==============================================  ==========================================================
class                                           cycles
==============================================  ==========================================================
ALU, MOV, compare, shifts, extends, IT, NOP     1
MUL, SMLAD, SMLA*, SMUL*, SXTB16                1;  MLA, MLS 2;  SDIV, UDIV 12 (worst case)
LDR*, STR* (one register)                       2   (no credit for pipelined neighbours: conservative)
LDRD, STRD                                      3   (1 + N, N = 2 words)
LDM, STM, PUSH, POP (N registers)               1 + N   (+P when PC is loaded)
branch (B, BL, BX, CBZ, ...), taken              1 + P, P = 2 (pipeline refill, TRM range 1-3)
branch not taken                                1
VADD, VSUB, VMUL, VNEG, VABS, VCMP, VCVT, VMOV  1   (VMOV of two core registers 2)
VMRS, VMSR                                      1
VMLA, VMLS, VFMA, VFMS, VNMLA, ... (MAC)         3
VDIV, VSQRT                                     14
VLDR, VSTR                                      2   (.64: 3)
VLDM, VSTM, VPUSH, VPOP (N words)               1 + N
==============================================  ==========================================================

On top of that, flash wait states (``flash_stalls``). Main SRAM (0x2000_0000) and CCM RAM (0x1000_0000) have zero
wait states: RM0090 (STM32F405 reference manual) section 2.3.1, "Embedded SRAM": read and write operations on the
system SRAM are performed at CPU speed with 0 wait state; CCM is on the core's D-bus. So the ``ram`` and ``ccm``
placements of the tables cost the same cycles here; ``ram`` is the default because the stock firmware leaves
37 KB of SRAM but 0.6 KB of CCM free (``firmware_export.fw_budget``). The STM32F405's flash needs 5 wait states at 168 MHz (RM0090, Table 10); its ART accelerator reads
128-bit lines and keeps 64 of them in an instruction cache and 8 in a data cache (RM0090, section 3.5.2). The
model follows every executed instruction's line and every data read of a flash address (a unicorn memory hook)
through two LRU caches of those sizes, both cold at the start of the call (the rest of the firmware runs
between two inferences), and charges 5 cycles per miss. What it does not model, and in which direction:

- the instruction prefetch buffer, which fetches the next sequential line while the current one executes and
  hides part of an instruction miss: not credited (pessimistic for code; the inner loops stay in the cache);
- data reads get no prefetch on the STM32F4 (the prefetch serves the I-code bus only), so a weight stream from
  flash misses once per 16 bytes whatever the access pattern: exact for that part under this model;
- the replacement policy of the ART caches is not documented; LRU is assumed;
- bus-matrix contention with DMA (SRAM only; CCM and flash reads by the core see none from DMA: on the Crazyflie
  the radio UART, the sensors' SPI/I2C and the LED ring use DMA; a DMA transfer into SRAM1 while the core reads it
  delays the core's access by the arbitration; the tables sit wherever the linker puts ``.bss``) and interrupts;
- the pipelining of neighbouring single loads and stores (TRM: an LDR after an LDR can take 1 cycle): every LDR/STR
  is charged 2 cycles, LDRD/STRD 3.
"""
from __future__ import annotations

import re
import subprocess
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_export.mlp_graph import CExportError
from firmware_export.toolchain import (ARM_GCC, CCM_BASE, CCM_BYTES, FLASH_BASE, RAM_BASE, SectionSizes,
                                       compile_m4_object, link_m4_elf, object_sizes)

CLOCK_HZ = 168_000_000
"""STM32F405 core clock on the Crazyflie 2.x."""
REFILL = 2
"""P: pipeline refill cycles after a taken branch (TRM: 1 to 3)."""
FLASH_WAIT_STATES = 5
"""STM32F405 flash latency at 168 MHz and 3.3 V (RM0090, Table 10)."""
FLASH_LINE_BYTES = 16
ART_ICACHE_LINES = 64
ART_DCACHE_LINES = 8
_RETURN = 0x0810_0000
_OBS_ADDR = RAM_BASE + 0x1_F000
"""The call's arguments sit at the top of SRAM, above the stack; ``.data``/``.bss`` (the ``ram`` tables' copy)
start at the bottom."""
_ACT_ADDR = RAM_BASE + 0x1_F800
_STACK_TOP = RAM_BASE + 0x1_F000
_STACK_ROOM = 0x4000
_BRANCHES = re.compile(r"^(b|bl|blx|bx|cbz|cbnz|tbb|tbh)(eq|ne|cs|hs|cc|lo|mi|pl|vs|vc|hi|ls|ge|lt|gt|le|al)?"
                       r"(\.n|\.w)?$")


class EmulatorError(CExportError):
    """The emulator (unicorn) is missing or the M4 build did not run to completion."""


@dataclass(frozen=True)
class Instr:
    size: int
    mnemonic: str
    operands: str


@dataclass(frozen=True)
class FlashStalls:
    icache_misses: int
    dcache_misses: int
    flash_data_reads: int
    """Data reads (words) of flash addresses: literal pools, and the tables when they are read in place."""
    ccm_data_reads: int
    """Data reads (words) of CCM addresses: the tables' working copy with ``--weights-in ccm``."""
    ram_table_reads: int = 0
    """Data reads of the static SRAM (``.data``/``.bss``, not the stack): the tables' copy with ``ram``."""

    @property
    def cycles(self) -> int:
        return FLASH_WAIT_STATES * (self.icache_misses + self.dcache_misses)


@dataclass(frozen=True)
class M4Run:
    act: np.ndarray
    instructions: int
    cycles: int
    """Zero-wait-state cycles (TRM timing of each executed instruction)."""
    by_class: dict[str, tuple[int, int]]
    """Instruction class -> (executed instructions, cycles)."""
    stalls: FlashStalls | None = None
    init_instructions: int = 0
    init_cycles: int = 0
    """``swarm_policy_init`` (the copy to CCM), once at start-up, wait states included."""

    @property
    def total_cycles(self) -> int:
        """Cycles of one inference with the flash wait states of the ART cache model."""
        return self.cycles + (self.stalls.cycles if self.stalls is not None else 0)


@dataclass(frozen=True)
class M4Build:
    elf: Path
    obj: Path
    sizes: SectionSizes
    entry: int
    init: int
    """Address of ``swarm_policy_init``."""
    flash: bytes
    listing: dict[int, Instr]


def build(c_file: Path, work: Path) -> M4Build:
    """Compile and link ``c_file`` (a generated policy.c beside its policy.h) for the Cortex-M4."""
    work.mkdir(parents=True, exist_ok=True)
    return build_from_object(compile_m4_object(c_file, work / "policy_m4.o", include=(c_file.parent,)), work)


def build_from_object(obj: Path, work: Path) -> M4Build:
    """Link a compiled policy object for emulation: ``build``'s, or the ``src/policy.o`` a firmware build of the
    Crazyflie app made (to run exactly what the firmware links)."""
    work.mkdir(parents=True, exist_ok=True)
    elf = link_m4_elf([obj], work / "policy_m4.elf")
    tool = ARM_GCC.replace("gcc", "")
    flash = work / "policy_m4_flash.bin"
    subprocess.run([tool + "objcopy", "-O", "binary", "-j", ".text", "-j", ".rodata", str(elf), str(flash)],
                   check=True, capture_output=True)
    nm = subprocess.run([tool + "nm", str(elf)], check=True, capture_output=True, text=True).stdout
    syms = {p[2]: int(p[0], 16) for p in (line.split() for line in nm.splitlines()) if len(p) == 3}
    dis = subprocess.run([tool + "objdump", "-d", str(elf)], check=True, capture_output=True, text=True).stdout
    return M4Build(elf, obj, object_sizes(obj), syms["swarm_policy_act"], syms["swarm_policy_init"], flash.read_bytes(),
                   parse_listing(dis))


def parse_listing(objdump: str) -> dict[int, Instr]:
    """address -> instruction from ``objdump -d`` text."""
    out: dict[int, Instr] = {}
    for line in objdump.splitlines():
        m = re.match(r"^\s*([0-9a-f]+):\t([0-9a-f ]+?)\s*\t(\S+)\s*([^@;]*)", line)
        if not m or m.group(3).startswith("."):
            continue
        nbytes = sum(len(h) // 2 for h in m.group(2).split())
        out[int(m.group(1), 16)] = Instr(nbytes, m.group(3), m.group(4).strip())
    return out


def _reglist_words(ops: str) -> int:
    inner = ops[ops.index("{") + 1:ops.index("}")]
    n = 0
    for part in inner.split(","):
        part = part.strip()
        if "-" in part:
            a, b = part.split("-")
            n_regs = int(b[1:]) - int(a[1:]) + 1
        else:
            n_regs, a = 1, part
        n += n_regs * (2 if a.startswith("d") else 1)
    return n


def instr_cycles(ins: Instr, taken: bool) -> tuple[str, int]:
    """(class, cycles) of one executed instruction under the model in this module's docstring."""
    m, ops = ins.mnemonic.lower(), ins.operands.lower()
    base = m.split(".")[0]
    if base.startswith("v"):
        if base in ("vldmia", "vldmdb", "vldm", "vstmia", "vstmdb", "vstm", "vpush", "vpop"):
            return "fp load/store multiple", 1 + _reglist_words(ops)
        if base in ("vldr", "vstr"):
            return "fp load/store", 3 if ops.startswith("d") else 2
        if base in ("vmla", "vmls", "vnmla", "vnmls", "vfma", "vfms", "vfnma", "vfnms"):
            return "fp multiply-accumulate", 3
        if base in ("vdiv", "vsqrt"):
            return "fp divide/sqrt", 14
        if base == "vmov" and ops.count(",") >= 2:
            return "fp move", 2
        return "fp arithmetic/move", 1
    if _BRANCHES.match(m) or (base in ("pop", "ldm", "ldmia") and "pc" in ops) or (
            base.startswith("ldr") and ops.startswith("pc")):
        if base in ("pop", "ldm", "ldmia"):
            return "branch", 1 + _reglist_words(ops) + (REFILL if taken else 0)
        return "branch", 1 + (REFILL if taken else 0)
    if base in ("ldm", "ldmia", "ldmdb", "stm", "stmia", "stmdb", "push", "pop"):
        return "load/store multiple", 1 + _reglist_words(ops)
    if base in ("ldrd", "strd"):
        return "load/store", 3
    if base.startswith(("ldr", "str")):
        return "load/store", 2
    if base in ("mla", "mls"):
        return "multiply", 2
    if base in ("sdiv", "udiv"):
        return "divide", 12
    if base.startswith(("mul", "smla", "smul", "smlad", "umull", "smull")):
        return "multiply", 1
    return "integer", 1


def _lru_misses(lines, size: int) -> int:
    cache: OrderedDict[int, None] = OrderedDict()
    misses = 0
    for line in lines:
        if line in cache:
            cache.move_to_end(line)
            continue
        misses += 1
        cache[line] = None
        if len(cache) > size:
            cache.popitem(last=False)
    return misses


def flash_stalls(b: M4Build, trace: list[int], reads: list[int]) -> FlashStalls:
    """The ART cache model of this module's docstring over one call's executed addresses and data reads."""
    ilines = []
    for addr in trace:
        first, last = addr // FLASH_LINE_BYTES, (addr + b.listing[addr].size - 1) // FLASH_LINE_BYTES
        ilines.append(first)
        if last != first:
            ilines.append(last)
    flash_reads = [a for a in reads if FLASH_BASE <= a < FLASH_BASE + (1 << 20)]
    ccm_reads = sum(1 for a in reads if CCM_BASE <= a < CCM_BASE + CCM_BYTES)
    static_end = RAM_BASE + b.sizes.data + b.sizes.bss
    ram_reads = sum(1 for a in reads if RAM_BASE <= a < static_end)
    return FlashStalls(_lru_misses(ilines, ART_ICACHE_LINES),
                       _lru_misses((a // FLASH_LINE_BYTES for a in flash_reads), ART_DCACHE_LINES),
                       len(flash_reads), ccm_reads, ram_reads)


def _count(b: M4Build, trace: list[int], end: int) -> tuple[int, dict[str, list[int]]]:
    by_class: dict[str, list[int]] = {}
    total = 0
    for i, addr in enumerate(trace):
        ins = b.listing.get(addr)
        if ins is None:
            raise EmulatorError(f"executed address {addr:#x} is not in the disassembly of {b.elf}")
        nxt = trace[i + 1] if i + 1 < len(trace) else end
        cls, cyc = instr_cycles(ins, taken=nxt != addr + ins.size)
        slot = by_class.setdefault(cls, [0, 0])
        slot[0] += 1
        slot[1] += cyc
        total += cyc
    return total, by_class


def run(b: M4Build, obs: np.ndarray, act_dim: int = 2, count: bool = True) -> M4Run:
    """``swarm_policy_init()`` then one ``swarm_policy_act(obs, act)`` on the emulated Cortex-M4 (flash, SRAM
    and CCM mapped as on the STM32F405)."""
    try:
        from unicorn import (UC_ARCH_ARM, UC_HOOK_CODE, UC_HOOK_MEM_READ, UC_MODE_MCLASS, UC_MODE_THUMB, Uc,
                             UcError)
        from unicorn import arm_const as ac
    except ImportError:
        raise EmulatorError("the unicorn emulator is not installed: pip install unicorn "
                            "(it is in the project's dev extra)") from None
    if b.sizes.data + b.sizes.bss > _STACK_TOP - RAM_BASE - _STACK_ROOM:
        raise EmulatorError(f"{b.sizes.data + b.sizes.bss} B of static RAM leave no room for the stack in the "
                            "emulator's 128 KB SRAM: export with smaller tables or --weights-in flash")
    uc = Uc(UC_ARCH_ARM, UC_MODE_THUMB | UC_MODE_MCLASS)
    uc.ctl_set_cpu_model(ac.UC_CPU_ARM_CORTEX_M4)
    uc.mem_map(FLASH_BASE, 1 << 20)
    uc.mem_map(RAM_BASE, 128 << 10)
    uc.mem_map(CCM_BASE, CCM_BYTES)
    uc.mem_map(_RETURN, 0x1000)
    uc.mem_write(FLASH_BASE, b.flash)
    trace: list[int] = []
    reads: list[int] = []
    if count:
        uc.hook_add(UC_HOOK_CODE, lambda _uc, addr, _size, _data: trace.append(addr))
        uc.hook_add(UC_HOOK_MEM_READ, lambda _uc, _access, addr, _size, _value, _data: reads.append(addr))

    def call(entry: int, r0: int = 0, r1: int = 0) -> None:
        uc.reg_write(ac.UC_ARM_REG_R0, r0)
        uc.reg_write(ac.UC_ARM_REG_R1, r1)
        uc.reg_write(ac.UC_ARM_REG_SP, _STACK_TOP)
        uc.reg_write(ac.UC_ARM_REG_LR, _RETURN | 1)
        try:
            uc.emu_start(entry | 1, _RETURN, count=5_000_000)
        except UcError as exc:
            raise EmulatorError(f"the M4 build faulted at {uc.reg_read(ac.UC_ARM_REG_PC):#x}: {exc}") from None
        if uc.reg_read(ac.UC_ARM_REG_PC) & ~1 != _RETURN:
            raise EmulatorError("the policy did not return within 5,000,000 instructions")

    call(b.init)
    init_trace, init_reads = list(trace), list(reads)
    trace.clear()
    reads.clear()
    uc.mem_write(_OBS_ADDR, np.ascontiguousarray(obs, dtype=np.float32).tobytes())
    call(b.entry, _OBS_ADDR, _ACT_ADDR)
    act = np.frombuffer(bytes(uc.mem_read(_ACT_ADDR, 4 * act_dim)), np.float32).copy()
    if not count:
        return M4Run(act, 0, 0, {})
    total, by_class = _count(b, trace, _RETURN)
    init_total, _ = _count(b, init_trace, _RETURN)
    init_stalls = flash_stalls(b, init_trace, init_reads)
    return M4Run(act, len(trace), total, {k: (v[0], v[1]) for k, v in sorted(by_class.items())},
                 flash_stalls(b, trace, reads), len(init_trace), init_total + init_stalls.cycles)


def micros(cycles: int) -> float:
    return cycles / CLOCK_HZ * 1e6
