#!/bin/sh
# tests/mutants/run.sh -- mutation testing of the test suite ("make mutants").
#
# Each mutant in tests/mutants/mutants.txt removes or weakens one mechanism
# the tests are meant to guard: a search-and-replace of one exact piece of
# text in one file (no line numbers, so a mutant survives edits elsewhere).
# For each mutant the script copies the tree (sources, README.md, which
# the drift: tests read, and build/, so only the mutated file is
# recompiled), applies the replacement, rebuilds with make -j2 and runs
# build/run_tests with the mutant's test filters.  The
# mutant must make them fail, FOR ITS MECHANISM: the entry's `expect`
# names a piece of the failure message that the broken mechanism causes,
# and some FAIL line must contain it.  A mutant that dies of a side
# effect (a NaN that fails another check, a crash, a timeout) has not
# shown that a test guards its mechanism.  The table it prints says, for
# each mutant:
#   killed    a selected test failed with the expected message (the FAIL
#             lines name which; the first message is shown)
#   SURVIVED  every selected test passed: the mechanism is unguarded
#   WRONG     the tests failed, but not with the expected message, or by a
#             crash or a timeout: the mutant or its expect needs a look
#             (`expect: crash` is for a guard of memory safety alone)
#   ERROR     the original text is not in the file, or is there more than
#             once (the list needs updating), or the mutant does not build
# Usage: sh tests/mutants/run.sh [NAME-SUBSTRING...]   (no argument: all)
# Environment: MUTANTS_TESTS='FILTER|...' runs those tests for every mutant
# instead of its own filters ('' with MUTANTS_ALL=1: the whole suite);
# MUTANTS_LIST another list; MUTANTS_TIMEOUT seconds per run (default 300).
# Exit status: 0 when every mutant was killed, 1 otherwise.
set -u
root=$(cd "$(dirname "$0")/../.." && pwd)
list=${MUTANTS_LIST:-$root/tests/mutants/mutants.txt}
timeout_s=${MUTANTS_TIMEOUT:-300}
shared=${BRT_SHARED:-$root/../shared}
case $shared in /*) ;; *) shared=$root/$shared ;; esac
scratch=$(mktemp -d "${TMPDIR:-/tmp}/batchrt-mutants.XXXXXX") || exit 1
trap 'rm -rf "$scratch"' EXIT INT TERM
limit=
command -v timeout >/dev/null 2>&1 && limit="timeout $timeout_s"   # not POSIX: optional

# The pristine tree, built once; every mutant starts from a copy of it
# (cp -p keeps the times, so make recompiles only what the mutant touches).
make -C "$root" --no-print-directory -j2 all build/run_tests >"$scratch/base.log" 2>&1 || {
    cat "$scratch/base.log"; echo "mutants: the unmutated tree does not build"; exit 1; }
mkdir "$scratch/base"
(cd "$root" && cp -p Makefile README.md ./*.c ./*.h "$scratch/base/" && cp -Rp examples tests "$scratch/base/") || exit 1
mkdir "$scratch/base/build"
for f in "$root"/build/*; do
    case ${f##*/} in debug|sanitize|valgrind|fuzz|demo|fig|*.png|*.brs) continue ;; esac
    cp -Rp "$f" "$scratch/base/build/" || exit 1
done

# Applies FIND -> REPL (literal text, one line) to file $1 in place; prints
# how many times FIND occurs.  The strings travel through the environment:
# awk -v would interpret their backslashes.
apply() {
    awk -v count="$1.count" '
        BEGIN { f = ENVIRON["FIND"]; r = ENVIRON["REPL"]; n = 0 }
        {   line = $0; out = ""
            while (f != "" && (i = index(line, f)) > 0) {
                n++; out = out substr(line, 1, i - 1) r; line = substr(line, i + length(f))
            }
            print out line }
        END { print n > count }' "$1" >"$1.new" && mv "$1.new" "$1" && cat "$1.count" && rm -f "$1.count"
}

selected() {
    [ $# -eq 0 ] && return 0
    for pat in "$@"; do case $name in *"$pat"*) return 0 ;; esac; done
    return 1
}

total=0; killed=0; survived=0; errors=0; wrong=0
printf '| mutant | mechanism | killed? | by | first failure |\n|---|---|---|---|---|\n'
run_one() {
    total=$((total + 1))
    dir=$scratch/m
    rm -rf "$dir" && cp -Rp "$scratch/base" "$dir" || exit 1
    n=$(FIND=$find REPL=$repl apply "$dir/$file" 2>/dev/null)
    if [ "$n" != 1 ]; then
        errors=$((errors + 1))
        printf '| %s | %s | ERROR | original text found %s times in %s | |\n' "$name" "$mech" "${n:-0}" "$file"
        return
    fi
    run=${MUTANTS_TESTS-$tests}
    [ "${MUTANTS_ALL:-0}" = 1 ] && run=
    # build/mpi_trace too when the pristine tree has it (make mpi), and its
    # test build with small thresholds (build/tests/mpi_trace_small), when
    # the selected tests may run them (all, or a filter naming mpi): the MPI
    # mutants are killed only where MPI runs (tests/test_mpi.c skips else).
    mpi=
    case $run in ''|*mpi*) mpi=1 ;; esac
    # build/embree_trace too when the pristine tree has it (make embree):
    # it shares examples/lib with the other programs.
    if ! make -C "$dir" --no-print-directory -j2 all build/run_tests \
            $([ -x "$root/build/embree_trace" ] && echo build/embree_trace) \
            $([ -n "$mpi" ] && [ -x "$root/build/mpi_trace" ] && echo build/mpi_trace) \
            $([ -n "$mpi" ] && [ -x "$root/build/tests/mpi_trace_small" ] && echo build/tests/mpi_trace_small) \
            >"$dir/build.log" 2>&1; then
        errors=$((errors + 1))
        printf '| %s | %s | ERROR | does not build | |\n' "$name" "$mech"
        return
    fi
    old_ifs=$IFS; IFS='|'; set -f; set -- $run; set +f; IFS=$old_ifs
    # (run by an inner shell, so its "Segmentation fault" note goes to the log)
    # Each mutant's run gets a scratch root of its own (TMPDIR), removed
    # with its copy of the tree: a mutant that crashes or hangs the runner
    # leaves nothing behind in the system's temporary folder.
    mkdir "$dir/tmp"
    sh -c 'limit=$2; d=$1; cd "$d" && shift 3 && TMPDIR=$d/tmp BRT_BUILD=build BRT_SHARED=$0 $limit ./build/run_tests "$@"; exit $?' \
        "$shared" "$dir" "$limit" - "$@" </dev/null >"$dir/test.log" 2>&1
    status=$?
    by=$(awk '/^FAIL / { i = index($0, ": tests/"); if (i > 6) print substr($0, 6, i - 6) }' \
             "$dir/test.log" | sort -u | awk 'NR > 1 { printf ", " } { printf "%s", $0 }')
    # The first FAIL line's message, without "FAIL name: file:line: " and
    # the seed (a table cell: no | characters).
    first=$(awk '/^FAIL / { i = index($0, ": tests/"); m = substr($0, i + 2); sub(/^[^ ]*: /, "", m);
                sub(/ \(seed [0-9]*\)$/, "", m); gsub(/\|/, "/", m); print substr(m, 1, 120); exit }' "$dir/test.log")
    if [ "$status" -eq 0 ]; then
        survived=$((survived + 1))
        # a test that said SKIP (no MPI, no Embree) cannot kill: say so
        skips=$(grep -c '^SKIP ' "$dir/test.log")
        printf '| %s | %s | SURVIVED | (ran: %s%s) | |\n' "$name" "$mech" "${run:-all}" \
            "$([ "$skips" -gt 0 ] && echo "; $skips skipped")"
        return
    fi
    verdict=yes
    crashed=0
    grep -q '^FAIL .*(a crash)$' "$dir/test.log" && crashed=1
    if [ "$status" -eq 124 ]; then by="${by:+$by, }timeout after ${timeout_s}s"; verdict=WRONG
    elif [ "$status" -gt 128 ]; then
        by="${by:+$by, }crash (signal $((status - 128)))"; crashed=1
    fi
    # "expect: crash" is for a guard of memory safety, whose absence can
    # only show as a crash; any other mutant that crashes died of a side
    # effect.
    if [ "$expect" = crash ]; then [ "$crashed" = 1 ] || verdict=WRONG
    elif [ "$crashed" = 1 ]; then verdict=WRONG
    elif [ -n "$expect" ] && ! grep '^FAIL ' "$dir/test.log" | grep -F -q -- "$expect"; then verdict=WRONG; fi
    if [ "$verdict" = yes ]; then killed=$((killed + 1)); else wrong=$((wrong + 1)); fi
    printf '| %s | %s | %s | %s | %s |\n' "$name" "$mech" "$verdict" "${by:-exit status $status}" "$first"
}

# The list: blocks of "key: value" lines separated by blank lines; keys
# name, file, mechanism, tests (run_tests filters separated by |), find,
# replace, expect (a piece of the failure message the mechanism causes).
# Lines starting with # are comments.
name=; file=; mech=; tests=; find=; repl=; have_repl=0; expect=
flush() {
    if [ -n "$name" ] && selected "$@"; then
        if [ -z "$file" ] || [ -z "$find" ] || [ "$have_repl" = 0 ]; then
            errors=$((errors + 1)); total=$((total + 1))
            printf '| %s | %s | ERROR | incomplete entry in mutants.txt |\n' "$name" "$mech"
        else
            run_one
        fi
    fi
    name=; file=; mech=; tests=; find=; repl=; have_repl=0; expect=
}
while IFS= read -r line || [ -n "$line" ]; do
    case $line in
    '#'*) continue ;;
    '') flush "$@"; continue ;;
    esac
    key=${line%%:*}
    value=${line#*:}
    value=${value#"${value%%[! ]*}"}        # leading blanks
    case $key in
    name) name=$value ;;
    file) file=$value ;;
    mechanism) mech=$value ;;
    tests) tests=$value ;;
    find) find=$value ;;
    replace) repl=$value; have_repl=1 ;;
    expect) expect=$value ;;
    *) echo "mutants.txt: unknown key '$key'" >&2; exit 1 ;;
    esac
done <"$list"
flush "$@"

echo
echo "$total mutants: $killed killed, $survived survived, $wrong killed by the wrong failure, $errors errors"
[ "$survived" -eq 0 ] && [ "$errors" -eq 0 ] && [ "$wrong" -eq 0 ]
