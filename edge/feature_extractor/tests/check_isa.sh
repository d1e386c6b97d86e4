#!/usr/bin/env bash
# The portable build holds no instruction past its baseline (x86-64-v2) outside the paths entered only
# on a CPU that has them: the scan's ft_fx_*_avx2 / _avx512bw (src/scan_avx2.c, scan_avx512bw.c) and
# GCC's target clones *.arch_x86_64_v3 / v4 (src/thresholds.h). Anything else wide would kill the
# binary with an illegal instruction on an older camera computer. Wide: a VEX or EVEX instruction
# (AVX, AVX2, AVX-512, FMA: mnemonics v*, or ymm/zmm/mask registers) or BMI/LZCNT/MOVBE.
# (tzcnt is shown for rep bsf, which older CPUs run as bsf: GCC emits it for x86-64-v2 too.)
# Usage: check_isa.sh BINARY...  Exit 1 naming each function at fault; 2 when nothing was checked.
#        check_isa.sh --expect-fault BINARY...  The check itself checked: exit 0 only if it finds a
#        fault in every binary given (a build with wide instructions everywhere).
set -euo pipefail
if [ "${1:-}" = --expect-fault ]; then
  shift
  for bin in "$@"; do
    rc=0
    "$0" "$bin" >/dev/null || rc=$?
    [ "$rc" -eq 1 ] || { echo "$bin: the check found no fault (exit $rc) in a binary that has some" >&2; exit 1; }
  done
  echo "check_isa: found the wide instructions of $*"
  exit 0
fi
status=0
for bin in "$@"; do
  objdump -d --no-show-raw-insn "$bin" | awk -v bin="$bin" '
    /^[0-9a-f]+ <.*>:$/ { fn = substr($2, 2, length($2) - 3); nfn++; next }
    /^ +[0-9a-f]+:\t/ {
      split($0, part, "\t"); insn = part[2]; split(insn, w, " "); m = w[1]
      wide = m ~ /^v/ || insn ~ /%[yz]mm[0-9]|%k[0-7]/ ||
             m ~ /^(andn|bextr|blsi|blsmsk|blsr|bzhi|pdep|pext|rorx|sarx|shlx|shrx|lzcnt|mulx|movbe)$/
      if (!wide) next
      if (fn ~ /(_avx2|_avx512bw|\.arch_x86_64_v[34])(\.cold|\.part\.[0-9]+|\.constprop\.[0-9]+|\.isra\.[0-9]+)*$/) {
        allowed[fn] = 1; next
      }
      if (!(fn in bad)) { bad[fn] = insn; nbad++ }
    }
    END {
      for (f in bad) printf "%s: %s uses %s outside a dispatched path\n", bin, f, bad[f]
      na = 0; for (f in allowed) na++
      if (nfn == 0) { printf "%s: no functions disassembled\n", bin; exit 2 }
      if (nbad) exit 1
      printf "%s: %d functions, wide instructions only in the %d dispatched ones\n", bin, nfn, na
    }' || status=$?
  [ "$status" -eq 0 ] || break
done
exit "$status"
