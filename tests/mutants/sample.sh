#!/bin/sh
# tests/mutants/sample.sh -- mutants nobody chose ("make mutants-sample").
#
# tests/mutants/mutants.txt holds mutants that their authors wrote next to
# their tests, so the two fit each other.  This script draws mutants at
# random instead: it lists every place in FILES where a mutation operator
# applies, draws lines at random (seeded), applies one operator at each,
# builds the mutant in a copy of the tree and runs the WHOLE suite with
# BRT_TEST_FAILFAST=1 (a mutant is killed by its first failure).  The
# operators, the classic ones of mutation testing:
#   comparison   <  <=  >  >=  ==  != : the boundary moved or the test flipped
#   arithmetic   +  -  /  ++  --  +=  -= : the other operation
#   boolean      &&  || : the other one; a ! dropped
#   constant     an integer literal n: n + 1 (0 and 1 swap)
#   statement    a line that is a whole statement (ends in ;) deleted
#   guard        if ( -> if (1 || : the guard always taken
# A mutant that does not build is drawn again (it says nothing about the
# tests).  tests/mutants/equivalent.txt lists mutants that change no
# behaviour, with the reason; they are drawn, shown and not counted.
#
# Usage: sh tests/mutants/sample.sh [N] [SEED] FILE...
#   (make mutants-sample N=40 SEED=1 FILES="batchrt.c examples/lib/pbrt.c")
# Prints one Markdown row per mutant, the survivors' diffs, and the kill
# rate among the mutants that are not equivalent.  Environment:
# MUTANTS_TIMEOUT seconds per suite run (default 900; a timeout kills).
# Exit status: 0 always (a sample is a measurement, not a gate).
set -u
n_wanted=${1:-40}
seed=${2:-1}
shift 2 2>/dev/null || shift $#
root=$(cd "$(dirname "$0")/../.." && pwd)
[ $# -gt 0 ] || set -- batchrt.c scene.c world.c mesh.c bvh.c svdag.c base.c
timeout_s=${MUTANTS_TIMEOUT:-900}
shared=${BRT_SHARED:-$root/../shared}
case $shared in /*) ;; *) shared=$root/$shared ;; esac
equivalent=$root/tests/mutants/equivalent.txt
scratch=$(mktemp -d "${TMPDIR:-/tmp}/batchrt-sample.XXXXXX") || exit 1
trap 'rm -rf "$scratch"' EXIT INT TERM
limit=
command -v timeout >/dev/null 2>&1 && limit="timeout $timeout_s"

make -C "$root" --no-print-directory -j2 all build/run_tests >"$scratch/base.log" 2>&1 || {
    cat "$scratch/base.log"; echo "mutants-sample: the unmutated tree does not build"; exit 1; }
mkdir "$scratch/base"
(cd "$root" && cp -p Makefile ./*.c ./*.h "$scratch/base/" && cp -Rp examples tests "$scratch/base/") || exit 1
mkdir "$scratch/base/build"
for f in "$root"/build/*; do
    case ${f##*/} in debug|sanitize|tsan|valgrind|fuzz|demo|fig|paper|inner|*.png|*.brs) continue ;; esac
    cp -Rp "$f" "$scratch/base/build/" || exit 1
done
have_mpi=; [ -x "$root/build/mpi_trace" ] && have_mpi=build/mpi_trace

# Every mutation site of every file, one per line:
#   file <TAB> line number <TAB> column <TAB> length <TAB> replacement
# Comments, string and character literals and preprocessor lines (but
# #define NAME value) are skipped.  An operator is taken only where its
# neighbours show it is that operator (a < not part of <<, <= or ->).
sites() {
    awk -v file="$1" '
    function site(col, len, rep) { printf "%s\t%d\t%d\t%d\t%s\n", file, NR, col, len, rep }
    {
        line = $0; code = ""; n = length(line); i = 1
        # The code of the line: comments and literals blanked (same columns).
        while (i <= n) {
            c = substr(line, i, 1); c2 = substr(line, i, 2)
            if (incomment) {
                if (c2 == "*/") { incomment = 0; code = code "  "; i += 2 } else { code = code " "; i++ }
            } else if (c2 == "/*") { incomment = 1; code = code "  "; i += 2 }
            else if (c2 == "//") { while (i <= n) { code = code " "; i++ } }
            else if (c == "\"" || c == "\047") {
                q = c; code = code " "; i++
                while (i <= n && substr(line, i, 1) != q) {
                    if (substr(line, i, 1) == "\\") { code = code " "; i++ }
                    code = code " "; i++
                }
                code = code " "; i++
            } else { code = code c; i++ }
        }
        if (code ~ /^[ \t]*$/) next
        if (code ~ /^[ \t]*#/ && code !~ /^[ \t]*#[ \t]*define[ \t]+[A-Za-z_0-9]+[ \t]+[(]?[0-9]/) next
        m = length(code)
        for (i = 1; i <= m; i++) {
            c = substr(code, i, 1); p = substr(code, i - 1, 1); nx = substr(code, i + 1, 1)
            c2 = substr(code, i, 2)
            if (c2 == "<=" && p != "<") { site(i, 2, "<"); i++; continue }
            if (c2 == ">=" && p != ">" && p != "-") { site(i, 2, ">"); i++; continue }
            if (c2 == "==") { site(i, 2, "!="); i++; continue }
            if (c2 == "!=") { site(i, 2, "=="); i++; continue }
            if (c2 == "&&") { site(i, 2, "||"); i++; continue }
            if (c2 == "||") { site(i, 2, "&&"); i++; continue }
            if (c2 == "++") { site(i, 2, "--"); i++; continue }
            if (c2 == "--") { site(i, 2, "++"); i++; continue }
            if (c2 == "+=") { site(i, 2, "-="); i++; continue }
            if (c2 == "-=") { site(i, 2, "+="); i++; continue }
            if (c2 == "<<" || c2 == ">>" || c2 == "->") { i++; continue }
            if (c == "<" && nx != "=" && code !~ /^[ \t]*#/) { site(i, 1, "<="); continue }
            if (c == ">" && nx != "=" && p != "-") { site(i, 1, ">="); continue }
            if (c == "+" && nx != "+" && nx != "=") { site(i, 1, "-"); continue }
            if (c == "-" && nx != "-" && nx != "=" && nx != ">" && p != "e" && p != "E") { site(i, 1, "+"); continue }
            if (c == "/" && nx != "=" && nx != "*" && p != "*") { site(i, 1, "*"); continue }
            if (c == "!" && nx != "=") { site(i, 1, ""); continue }
            if (c ~ /[0-9]/ && p !~ /[A-Za-z_0-9.]/) {
                j = i; while (substr(code, j + 1, 1) ~ /[0-9]/) j++
                after = substr(code, j + 1, 1)
                if (after !~ /[A-Za-z_.xX]/ || (after ~ /[uUlL]/ && substr(code, j + 2, 1) !~ /[A-Za-z_0-9.]/)) {
                    v = substr(code, i, j - i + 1) + 0
                    site(i, j - i + 1, v == 1 ? "0" : v + 1)
                }
                i = j; continue
            }
        }
        if (code ~ /;[ \t]*$/ && code ~ /^[ \t]*[a-z_A-Z(*]/ && code !~ /^[ \t]*(static|const|unsigned|int|double|float|char|size_t|uint[0-9]*_t|int[0-9]*_t|brt_[a-z_]*|struct|typedef|enum|return)[ \t*]/ &&
            code !~ /^[ \t]*(case|default|else|for|while|do)\b/)
            site(1, length(line), "")
        if (match(code, /(^|[^A-Za-z_0-9])if \(/)) site(RSTART + (RSTART > 1 ? 1 : 0), 4, "if (1 || ")
    }' "$root/$1"
}

: >"$scratch/sites"
for f in "$@"; do
    [ -f "$root/$f" ] || { echo "mutants-sample: no file $f"; exit 1; }
    sites "$f" >>"$scratch/sites"
done
lines=$(cut -f1,2 "$scratch/sites" | sort -u | wc -l)
echo "mutants-sample: $(wc -l <"$scratch/sites") sites on $lines lines of $*; N=$n_wanted, seed $seed"
echo

# The draw: a line at random among the lines that have sites, then one of
# its sites at random; a line is drawn once.  The order of the draws
# depends on the seed only, so a run can be repeated.
cut -f1,2 "$scratch/sites" | sort -u | awk -v seed="$seed" 'BEGIN { srand(seed) } { print rand() "\t" $0 }' |
    sort -k1,1 | cut -f2,3 >"$scratch/order"

# Applies site (file line col len rep) to the copy in $1; writes the
# original and the mutated line into $1/orig.line and $1/mut.line.
mutate() {
    awk -F'\t' -v ln="$3" -v col="$4" -v len="$5" -v rep="$6" -v out="$1/mut.line" -v orig="$1/orig.line" '
        NR == ln { print > orig; $0 = substr($0, 1, col - 1) rep substr($0, col + len); print > out }
        { print }' "$1/$2" >"$1/$2.new" && mv "$1/$2.new" "$1/$2"
}

total=0; killed=0; survived=0; equiv=0; drawn=0
: >"$scratch/results"
printf '| # | file:line | original | mutant | result |\n|---:|---|---|---|---|\n'
: >"$scratch/survivors"
while IFS='	' read -r file ln; do
    [ "$total" -ge "$n_wanted" ] && break
    drawn=$((drawn + 1))
    site=$(awk -F'\t' -v f="$file" -v l="$ln" '$1 == f && $2 == l' "$scratch/sites" |
           awk -v seed="$seed" -v d="$drawn" 'BEGIN { srand(seed * 7919 + d) } { s[NR] = $0 } END { print s[int(rand() * NR) + 1] }')
    col=$(echo "$site" | cut -f3); len=$(echo "$site" | cut -f4); rep=$(echo "$site" | cut -f5)
    dir=$scratch/m
    rm -rf "$dir" && cp -Rp "$scratch/base" "$dir" || exit 1
    mutate "$dir" "$file" "$ln" "$col" "$len" "$rep"
    orig=$(sed 's/^[ \t]*//' "$dir/orig.line"); mut=$(sed 's/^[ \t]*//' "$dir/mut.line")
    if ! make -C "$dir" --no-print-directory -j2 all build/run_tests $have_mpi >"$dir/build.log" 2>&1; then
        continue            # does not build: drawn again
    fi
    total=$((total + 1))
    cell() { printf '%s' "$1" | sed 's/|/\\|/g; s/`/'"'"'/g' | cut -c1-90; }
    mkdir "$dir/tmp"
    (cd "$dir" && TMPDIR=$dir/tmp BRT_BUILD=build BRT_SHARED=$shared BRT_TEST_FAILFAST=1 $limit ./build/run_tests \
        </dev/null >"$dir/test.log" 2>&1)
    status=$?
    if [ "$status" -ne 0 ]; then
        killed=$((killed + 1))
        by=$(awk '/^FAIL / { i = index($0, ": tests/"); print (i > 6 ? substr($0, 6, i - 6) : substr($0, 6)); exit }' "$dir/test.log")
        [ "$status" -eq 124 ] && by="timeout"
        result="killed: ${by:-status $status}"
    elif [ -f "$equivalent" ] && awk -F'\t' -v f="$file" -v o="$orig" -v m="$mut" \
            '$1 == f && $2 == o && $3 == m { found = 1 } END { exit !found }' "$equivalent"; then
        equiv=$((equiv + 1)); result="equivalent (tests/mutants/equivalent.txt)"
    else
        survived=$((survived + 1)); result="SURVIVED"
        { echo "--- $file:$ln"; echo "-$orig"; echo "+$mut"; echo; } >>"$scratch/survivors"
    fi
    printf '%s\t%s\n' "$file" "$result" >>"$scratch/results"
    printf '| %d | %s:%s | `%s` | `%s` | %s |\n' "$total" "$file" "$ln" "$(cell "$orig")" "$(cell "$mut")" "$(cell "$result")"
done <"$scratch/order"

echo
if [ -s "$scratch/survivors" ]; then
    echo "Survivors (a test is missing, or the mutant is equivalent: tests/mutants/equivalent.txt,"
    echo "one line each: file <TAB> original line <TAB> mutant line <TAB> why):"
    echo; cat "$scratch/survivors"
fi
# The last table: per file, and all together.
echo
echo "Seed $seed, $total mutants drawn from $lines lines:"
echo
awk -F'\t' '
    { if (!($1 in n)) order[++files] = $1; n[$1]++; r = $2 ~ /^killed/ ? "k" : $2 ~ /^equivalent/ ? "e" : "s"; c[$1, r]++; c["all", r]++ }
    function row(name, t, k, s, e) {
        printf "| %s | %d | %d | %d | %d | %s |\n", name, t, k, s, e, t - e ? sprintf("%.0f %%", 100 * k / (t - e)) : "-" }
    END {
        print "| file | mutants | killed | survived | equivalent | killed, of the not equivalent |"
        print "|---|---:|---:|---:|---:|---:|"
        for (i = 1; i <= files; i++) { x = order[i]; row(x, n[x], c[x, "k"], c[x, "s"], c[x, "e"]) }
        row("all", NR, c["all", "k"], c["all", "s"], c["all", "e"]) }' "$scratch/results"
