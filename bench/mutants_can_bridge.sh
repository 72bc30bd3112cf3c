#!/usr/bin/env bash
# Mutation testing of can_bridge's safety, receive and E2E code: every
# mutant (a changed operator, a deleted match arm, a function returning a
# constant) that no test fails on is a check no test pins. Target: none
# survives but those docs/bus-safety.md explains ("Mutation testing").
#
# Needs cargo-mutants (crates.io; once: `cargo install cargo-mutants --locked`).
# CPU heavy: one job (-j 1), the lib tests of the four modules and of the
# bridge that uses them (the proptests at 200 cases; the transports' pty
# tests are left out), a per-mutant timeout. Each module alone with FILES=..., a subset with
# RE=<regex of mutant names>:
#
#   bash bench/mutants_can_bridge.sh                       # the four modules, ~1.5 h
#   FILES=src/e2e.rs bash bench/mutants_can_bridge.sh      # one module
#   FILES=src/bridge/rx.rs RE='keeps_pace' bash bench/mutants_can_bridge.sh
#
# Results: $OUT/mutants.out/{caught,missed,timeout,unviable}.txt
# (OUT defaults to target/mutants).
set -euo pipefail
cd "$(dirname "$0")/../can_bridge"
if ! cargo mutants --version >/dev/null 2>&1; then
    echo "cargo-mutants is missing: cargo install cargo-mutants --locked" >&2
    exit 2
fi
FILES=${FILES:-"src/safety.rs src/bridge/rx.rs src/e2e.rs src/plausibility.rs"}
OUT=${OUT:-target/mutants}
# --copy-target: start from this tree's build (no dependency rebuild)
args=(-j 1 --timeout "${TIMEOUT:-60}" -C --lib --copy-target true -o "$OUT")
for f in $FILES; do
    args+=(-f "$f")
done
if [[ -n "${RE:-}" ]]; then
    args+=(--re "$RE")
fi
export CAN_BRIDGE_PROPTEST_CASES=${CAN_BRIDGE_PROPTEST_CASES:-200}
status=0
nice cargo mutants "${args[@]}" -- -- e2e:: plausibility:: bridge:: safety:: config:: ||
    status=$?
# cargo-mutants exits 2 when a mutant survived, 3 on a timeout
for kind in missed timeout; do
    f="$OUT/mutants.out/$kind.txt"
    if [[ -s "$f" ]]; then
        echo "$kind:"
        cat "$f"
    fi
done
exit "$status"
