#!/usr/bin/env bash
# Build the exported Crazyflie app inside a crazyflie-firmware checkout and print the firmware's flash, RAM and
# CCM use with the app in (the firmware's own tools/make/size.py lines, then the same figures against the stock
# firmware that firmware_export/fw_budget.py records).
#
#   firmware_export/check_in_firmware.sh CRAZYFLIE_BASE [APP_DIR]
#
# CRAZYFLIE_BASE  a checkout of bitcraze/crazyflie-firmware with its submodules (git clone --recursive)
# APP_DIR         an app written by `swarm-export c --app DIR`; without it, models/role_based/pursuer_0.onnx is
#                 exported with the default options (plus $SWARM_EXPORT_ARGS, e.g. "--quant int8w") to a
#                 temporary folder
# JOBS            parallel make jobs (default 2)
#
# Where the checkout's CMSIS copy lacks CMSIS/DSP/Source/CommonTables/arm_common_tables.c (a 1.6 MB file that
# partial clones miss), the tables the firmware links are generated there (firmware_export/cmsis_tables.py).
set -euo pipefail

usage() { echo "usage: $0 CRAZYFLIE_BASE [APP_DIR]" >&2; exit 2; }
[ $# -ge 1 ] && [ $# -le 2 ] || usage
here=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
py=${PYTHON:-python3}
[ -x "$here/.venv/bin/python" ] && py="$here/.venv/bin/python"

base=$(cd "$1" 2>/dev/null && pwd) || { echo "error: CRAZYFLIE_BASE $1 is not a folder: pass the firmware checkout" >&2; exit 2; }
[ -f "$base/tools/make/oot.mk" ] || { echo "error: $base has no tools/make/oot.mk: pass a bitcraze/crazyflie-firmware checkout" >&2; exit 2; }
for sub in vendor/FreeRTOS/include vendor/CMSIS/CMSIS/Core/Include vendor/libdw1000/inc; do
    [ -d "$base/$sub" ] || { echo "error: $base/$sub is missing: run git -C $base submodule update --init --recursive" >&2; exit 2; }
done
command -v arm-none-eabi-gcc >/dev/null || { echo "error: arm-none-eabi-gcc not found: apt-get install gcc-arm-none-eabi" >&2; exit 2; }

tables="$base/vendor/CMSIS/CMSIS/DSP/Source/CommonTables/arm_common_tables.c"
if [ ! -f "$tables" ]; then
    echo "note: $tables is missing from this CMSIS copy; generating the tables the firmware links"
    (cd "$here" && "$py" -m firmware_export.cmsis_tables "$tables")
fi

if [ $# -eq 2 ]; then
    app=$(cd "$2" && pwd)
else
    app=$(mktemp -d /tmp/swarm_cf_app.XXXXXX)
    # shellcheck disable=SC2086
    (cd "$here" && "$py" -m firmware_export.cli c --model models/role_based/pursuer_0.onnx --out "$app/c" \
        --app "$app" ${SWARM_EXPORT_ARGS:-})
fi

echo "firmware: $(git -C "$base" rev-parse HEAD 2>/dev/null || echo 'not a git checkout'), app: $app"
log="$app/check_in_firmware.log"
if ! nice -n 10 make -C "$app" CRAZYFLIE_BASE="$base" -j"${JOBS:-2}" >"$log" 2>&1; then
    grep -E "error|overflowed|will not fit" "$log" | head -20 >&2 || true
    echo "error: the firmware build with the app failed (full log: $log)" >&2
    exit 1
fi
grep -E "^(Flash|RAM|CCM) +\|" "$log"
(cd "$here" && "$py" -m firmware_export.fw_budget "$app/build/cf2.elf")
# the policy object exactly as the firmware compiled and linked it, run in the emulator
model=$(sed -n '1s/.*`swarm-export c` from \(.*\) -- do not edit.*/\1/p' "$app/src/policy.h")
if [ -n "$model" ] && [ -f "$here/$model" -o -f "$model" ]; then
    (cd "$here" && "$py" -m firmware_export.c_report --object "$app/src/policy.o" --model "$model") \
        || echo "note: could not emulate $app/src/policy.o (needs unicorn and onnxruntime)"
fi
