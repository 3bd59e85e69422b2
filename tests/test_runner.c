/*
** tests/test_runner.c -- the runner leaves nothing behind (tests/main.c).
**
** Runs build/run_tests itself with TMPDIR pointing at a fresh folder and
** its hidden test "runner: self-check", which leaves a file in its scratch
** folder and then fails, crashes or dies of SIGINT or SIGTERM.  Each time
** the runner must end as it should (exit 1, or killed by that signal) and
** the folder must end up empty.  The watcher that removes the scratch
** folder runs after the runner has died, so the test waits for it, up to
** a generous bound: a liveness check, not a timing.
*/
#include "test.h"
#include "util.h"

#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

static int is_empty(const char *dir)
{
    return tu_dir_entries(dir, NULL, NULL, NULL, 0) == 0;
}

/* Waits up to a minute for dir to be empty. */
static int becomes_empty(const char *dir)
{
    struct timespec pause = {0, 20 * 1000 * 1000};
    int i;
    for (i = 0; i < 3000; i++) {
        if (is_empty(dir)) return 1;
        nanosleep(&pause, NULL);
    }
    return 0;
}

/* Runs the runner's self-check in mode with TMPDIR = dir (and
** BRT_TEST_KEEP when keep): its status. */
static pid_t last_pid;          /* the runner run_selfcheck started last */

static int run_selfcheck(const char *mode, const char *dir, int keep)
{
    const char *build = getenv("BRT_BUILD");
    char runner[1024];
    int status = -1;
    pid_t pid;
    snprintf(runner, sizeof runner, "%s/run_tests", build ? build : "build");
    fflush(stdout);
    pid = fork();
    if (pid == 0) {
        int null = open("/dev/null", O_WRONLY);
        if (null >= 0) {
            dup2(null, 1);
            dup2(null, 2);
        }
        setpgid(0, 0);          /* a group of its own, for the group's SIGINT */
        /* As a terminal starts it: a shell's background job ignores SIGINT,
        ** and that would be inherited through exec. */
        signal(SIGINT, SIG_DFL);
        signal(SIGTERM, SIG_DFL);
        setenv("TMPDIR", dir, 1);
        setenv("BRT_TEST_SELFCHECK", mode, 1);
        if (keep) setenv("BRT_TEST_KEEP", "1", 1);
        else unsetenv("BRT_TEST_KEEP");
        execl(runner, runner, "runner: self-check", (char *)NULL);
        _exit(127);
    }
    if (pid > 0) waitpid(pid, &status, 0);
    last_pid = pid;
    return status;
}

static void test_scratch_removed(void)
{
    static const struct { const char *mode; int signal; } cases[] = {
        {"fail", 0}, {"segv", SIGSEGV}, {"abort", SIGABRT}, {"int", SIGINT}, {"term", SIGTERM}};
    size_t i;
    for (i = 0; i < sizeof cases / sizeof *cases; i++) {
        char dir[1024];
        int status, as_expected;
        snprintf(dir, sizeof dir, "%s/runner-%s", test_tmpdir(), cases[i].mode);
        CHECK(mkdir(dir, 0700) == 0 || is_empty(dir), "cannot make %s", dir);
        status = run_selfcheck(cases[i].mode, dir, 0);
        if (cases[i].signal == 0)
            as_expected = WIFEXITED(status) && WEXITSTATUS(status) == 1;
        else if (cases[i].signal == SIGINT || cases[i].signal == SIGTERM)
            as_expected = WIFSIGNALED(status) && WTERMSIG(status) == cases[i].signal;
        else   /* a sanitizer may catch the crash and exit non-zero instead */
            as_expected = (WIFSIGNALED(status) && WTERMSIG(status) == cases[i].signal) ||
                          (WIFEXITED(status) && WEXITSTATUS(status) != 0);
        EXPECT(as_expected, "self-check '%s': status %d", cases[i].mode, status);
        EXPECT(becomes_empty(dir), "self-check '%s' left its scratch folder in %s", cases[i].mode, dir);
    }
}

/* BRT_TEST_KEEP keeps the folder, and it is where TMPDIR says. */
static void test_scratch_kept_in_tmpdir(void)
{
    char dir[1024], cmd[2200];
    int status, found;
    snprintf(dir, sizeof dir, "%s/runner-keep", test_tmpdir());
    CHECK(mkdir(dir, 0700) == 0 || is_empty(dir), "cannot make %s", dir);
    status = run_selfcheck("fail", dir, 1);
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 1, "kept self-check: status %d", status);
    snprintf(cmd, sizeof cmd, "test -f %s/batchrt-test-*/left-behind", dir);
    found = system(cmd) == 0;
    EXPECT(found, "no scratch folder with the test's file under TMPDIR=%s", dir);
    snprintf(cmd, sizeof cmd, "rm -rf %s/batchrt-test-*", dir);
    EXPECT(system(cmd) == 0 && is_empty(dir), "could not clean %s", dir);
    /* Where a runner that ignored TMPDIR would have kept it. */
    snprintf(cmd, sizeof cmd, "rm -rf /tmp/batchrt-test-%ld", (long)last_pid);
    EXPECT(system(cmd) == 0, "could not clean /tmp");
}

/* Runs the runner with the self-check in mode beside the sampling tests,
** jobs workers and fail-fast or not (set either way: the suite itself
** may run under BRT_TEST_FAILFAST, as make mutants-sample runs it); its
** last line into last (or "").  Returns its status. */
static int run_mixed(const char *mode, const char *jobs, int fail_fast, char *last, size_t size)
{
    const char *build = getenv("BRT_BUILD");
    char cmd[3000], out[1024];
    int status;
    FILE *f;
    snprintf(out, sizeof out, "%s/runner-mixed.out", test_tmpdir());
    snprintf(cmd, sizeof cmd,
             "BRT_TEST_SELFCHECK=%s BRT_TEST_JOBS=%s BRT_TEST_FAILFAST=%s TMPDIR='%s' %s/run_tests "
             "'runner: self-check' sampling: > '%s' 2>&1",
             mode, jobs, fail_fast ? "1" : "", test_tmpdir(), build ? build : "build", out);
    status = system(cmd);
    last[0] = 0;
    f = fopen(out, "r");
    if (f) {
        char line[1024];
        while (fgets(line, sizeof line, f)) snprintf(last, size, "%s", line);
        fclose(f);
    }
    return status;
}

/* In parallel (two workers), a test that crashes is one FAIL line and
** every other test still runs; with BRT_TEST_FAILFAST no test starts
** after the first failure (one worker: the self-check is queued first). */
static void test_parallel_outcomes(void)
{
    char last[1024], expected[64];
    int status, sampling;
    status = run_mixed("fail", "1", 0, last, sizeof last);
    CHECK(sscanf(last, "%d passed, 1 failed", &sampling) == 1 && sampling > 1, "one worker: last line '%s'", last);
    status = run_mixed("segv", "2", 0, last, sizeof last);
    snprintf(expected, sizeof expected, "%d passed, 1 failed\n", sampling);
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 1, "a crash in parallel: status %d", status);
    EXPECT(strcmp(last, expected) == 0, "a crash in parallel: last line '%s', not '%s'", last, expected);
    status = run_mixed("fail", "1", 1, last, sizeof last);
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 1, "fail fast: status %d", status);
    EXPECT(strcmp(last, "0 passed, 1 failed\n") == 0, "fail fast: last line '%s'", last);
    {   /* ... and in parallel: the other worker ends with its running test,
        ** so not every sampling test runs (how many do depends on timing) */
        int passed = -1;
        status = run_mixed("fail", "2", 1, last, sizeof last);
        EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 1 && sscanf(last, "%d passed, 1 failed", &passed) == 1 &&
                   passed < sampling,
               "fail fast with two workers: last line '%s' (fewer than all %d)", last, sampling);
    }
    {   /* BRT_TEST_TIMES=1 lists the seconds slowest first */
        const char *build = getenv("BRT_BUILD");
        char cmd[2048], line[1024], out[1024];
        double previous = 1e300, seconds;
        int listed = 0, ordered = 1;
        FILE *f;
        snprintf(out, sizeof out, "%s/runner-times.out", test_tmpdir());
        snprintf(cmd, sizeof cmd, "BRT_TEST_TIMES=1 BRT_TEST_JOBS=1 BRT_TEST_FAILFAST= TMPDIR='%s' %s/run_tests sampling: "
                 "> '%s' 2>&1", test_tmpdir(), build ? build : "build", out);
        EXPECT(system(cmd) == 0, "BRT_TEST_TIMES=1 run failed");
        f = fopen(out, "r");
        while (f && fgets(line, sizeof line, f))
            if (strstr(line, " s  sampling:") && sscanf(line, "%lf", &seconds) == 1) {
                listed++;
                ordered &= seconds <= previous;
                previous = seconds;
            }
        if (f) fclose(f);
        EXPECT(listed > 1 && ordered, "BRT_TEST_TIMES=1: %d tests listed, slowest first: %d", listed, ordered);
    }
}

/* tests/contract.md pairs each statement of the README with the tests
** that fail when it turns false.  Every name it quotes (between
** backquotes, in the last cell of a row of a "| statement |" table) must
** be a test of the suite, and every statement must name one at least: a renamed or
** removed test cannot leave a statement unguarded without this failing. */
static void test_contract_names(void)
{
    FILE *f = fopen("tests/contract.md", "r");
    char line[4096];
    int rows = 0, names = 0, number = 0, in_statements = 0;
    CHECK(f, "cannot open tests/contract.md (run from the repository's top)");
    while (fgets(line, sizeof line, f)) {
        char *cell = strrchr(line, '|'), *p;
        int here = 0;
        number++;
        if (line[0] != '|') in_statements = 0;          /* a table ends at its first other line */
        if (strncmp(line, "| statement", 11) == 0) in_statements = 1;
        if (!in_statements || strncmp(line, "|---", 4) == 0 || strncmp(line, "| statement", 11) == 0) continue;
        *cell = 0;
        cell = strrchr(line, '|');
        rows++;
        for (p = strchr(cell, '`'); p; p = strchr(p + 1, '`')) {
            char *end = strchr(p + 1, '`');
            if (!end) break;
            *end = 0;
            here++;
            EXPECT(test_registered(p + 1), "tests/contract.md:%d: no test named '%s'", number, p + 1);
            p = end;
        }
        EXPECT(here > 0, "tests/contract.md:%d: a statement that names no test", number);
        names += here;
    }
    fclose(f);
    EXPECT(rows >= 50 && names >= rows, "tests/contract.md: %d statements, %d test names", rows, names);
}

/* The occurrences of needle in the file at path (-1: unreadable). */
static int occurrences(const char *path, const char *needle)
{
    size_t size = 0;
    char *text = (char *)tu_slurp(path, &size), *p;
    int n = 0;
    if (!text) return -1;
    for (p = strstr(text, needle); p && *needle; p = strstr(p + 1, needle)) n++;
    free(text);
    return n;
}

/* tests/mutants/mutants.txt stays applicable as the code moves: each
** entry's `find` occurs exactly once in its file (make mutants would say
** ERROR, but it runs for an hour; this takes a moment), and each names the
** failure it expects.  Values lose their leading blanks, as run.sh reads
** them. */
static void test_mutants_apply(void)
{
    FILE *f = fopen("tests/mutants/mutants.txt", "r");
    char line[4096], file[512] = "", find[4096] = "", name[256] = "";
    int entries = 0, have_expect = 0, number = 0, at = 0;
    CHECK(f, "cannot open tests/mutants/mutants.txt (run from the repository's top)");
    for (;;) {
        int end = !fgets(line, sizeof line, f);
        char *value;
        if (!end) number++;
        if (end || line[0] == '\n') {
            if (name[0]) {
                int n = occurrences(file, find);
                entries++;
                EXPECT(n == 1, "mutants.txt:%d: %s: its find occurs %d times in %s", at, name, n, file);
                EXPECT(have_expect, "mutants.txt:%d: %s names no expected failure", at, name);
            }
            name[0] = file[0] = find[0] = 0;
            have_expect = 0;
            if (end) break;
            continue;
        }
        if (line[0] == '#') continue;
        line[strcspn(line, "\n")] = 0;
        value = strchr(line, ':');
        if (!value) continue;
        *value++ = 0;
        value += strspn(value, " \t");
        if (strcmp(line, "name") == 0) { snprintf(name, sizeof name, "%s", value); at = number; }
        else if (strcmp(line, "file") == 0) snprintf(file, sizeof file, "%s", value);
        else if (strcmp(line, "find") == 0) snprintf(find, sizeof find, "%s", value);
        else if (strcmp(line, "expect") == 0) have_expect = *value != 0;
    }
    fclose(f);
    EXPECT(entries > 300, "only %d mutants in tests/mutants/mutants.txt", entries);
}

/* 1 when the n bytes at b hold the text s. */
static int bytes_hold(const unsigned char *b, size_t n, const char *s)
{
    size_t k = strlen(s), i;
    for (i = 0; b && i + k <= n; i++)
        if (memcmp(b + i, s, k) == 0) return 1;
    return 0;
}

/* README, "Set up" (make install): the library's hooks (testing.h) are
** compiled only into the copy this runner links ($BRT_BUILD/tests/
** libbatchrt_testing.a, BRT_TESTING); the release library defines none of
** them and holds no hook's variable, and the public header names none. */
static void test_hooks_only_in_tests(void)
{
    static const char *const hooks[] = {"brt_test_read_fault", "brt_test_early_reject",
                                        "brt_test_build_sizes"};
    const char *build = getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build";
    char lib[600], copy[600];
    unsigned char *a, *b, *h;
    size_t na = 0, nb = 0, nh = 0, i;
    snprintf(lib, sizeof lib, "%s/libbatchrt.a", build);
    snprintf(copy, sizeof copy, "%s/tests/libbatchrt_testing.a", build);
    a = tu_slurp(lib, &na);
    b = tu_slurp(copy, &nb);
    h = tu_slurp("batchrt.h", &nh);
    EXPECT(a && b && h, "cannot read %s, %s or batchrt.h", lib, copy);
    for (i = 0; a && b && h && i < sizeof hooks / sizeof hooks[0]; i++) {
        EXPECT(!bytes_hold(a, na, hooks[i]), "%s holds %s", lib, hooks[i]);
        EXPECT(bytes_hold(b, nb, hooks[i]), "%s lacks %s", copy, hooks[i]);
        EXPECT(!bytes_hold(h, nh, hooks[i]), "batchrt.h names %s", hooks[i]);
    }
    EXPECT(!a || !bytes_hold(a, na, "read_fault_after"), "%s holds the read fault's countdown", lib);
    EXPECT(!h || (!bytes_hold(h, nh, "test_spill_chunk") && !bytes_hold(h, nh, "test_bucket_tris")),
           "batchrt.h's brt_scene_options has a test field");
    free(a);
    free(b);
    free(h);
}

/* The brt_ symbols object o defines (defined) or needs (!defined), by
** nm; NULL when nm cannot run. */
static char *nm_symbols(const char *build, const char *o, int defined)
{
    char cmd[700], line[256], *all = calloc(1, 1);
    size_t n = 0;
    FILE *f;
    snprintf(cmd, sizeof cmd, "nm %s %s/%s.o 2>/dev/null", defined ? "--defined-only" : "-u", build, o);
    if (!all || !(f = popen(cmd, "r"))) return all;
    while (fgets(line, sizeof line, f)) {
        char *name = strrchr(line, ' ');
        char *grown;
        if (!name || strncmp(name + 1, "brt_", 4) != 0) continue;
        grown = realloc(all, n + strlen(name) + 1);
        if (!grown) break;
        all = grown;
        strcpy(all + n, name);              /* " name\n": a line, its blank first */
        n += strlen(name);
    }
    if (pclose(f) != 0) {
        free(all);
        return NULL;
    }
    return all;
}

/* internal.h, the layers: each core object needs brt_ symbols of its own
** row and the rows below only (nm): bvh.o and svdag.o nothing of
** batchrt.o, base.o nothing of any. */
static void test_core_layers(void)
{
    static const char *const rows[][3] = {{"batchrt", "scene", "world"}, {"mesh"}, {"svdag"},
                                          {"bvh"}, {"base"}};
    const int nrows = (int)(sizeof rows / sizeof rows[0]);
    const char *build = getenv("BRT_BUILD") ? getenv("BRT_BUILD") : "build";
    int r, k, above, j, checked = 0;
    for (r = 1; r < nrows; r++) {
        for (k = 0; k < 3 && rows[r][k]; k++) {
            char *needs = nm_symbols(build, rows[r][k], 0), *word, *end;
            if (!needs) {
                test_skip("nm cannot read %s/%s.o", build, rows[r][k]);
                return;
            }
            for (above = 0; above < r; above++)
                for (j = 0; j < 3 && rows[above][j]; j++) {
                    char *defs = nm_symbols(build, rows[above][j], 1);
                    CHECK(defs, "nm cannot read %s/%s.o", build, rows[above][j]);
                    for (word = needs; (end = strchr(word, '\n')) != NULL; word = end + 1) {
                        char need[300];
                        snprintf(need, sizeof need, "%.*s", (int)(end + 1 - word), word);
                        checked++;
                        EXPECT(!strstr(defs, need), "%s.o needs%.*s of %s.o, a row above it",
                               rows[r][k], (int)(end - word), word, rows[above][j]);
                    }
                    free(defs);
                }
            free(needs);
        }
    }
    EXPECT(checked > 20, "only %d needs checked: nm's output was not read", checked);
}

void suite_runner(void)
{
    test_run("runner: the scratch folder is removed on failure, crash, SIGINT and SIGTERM",
             test_scratch_removed);
    test_run("runner: the scratch folder goes to TMPDIR, kept with BRT_TEST_KEEP", test_scratch_kept_in_tmpdir);
    test_run("runner: in parallel a crash is one FAIL and the rest run; fail fast stops", test_parallel_outcomes);
    test_run("runner: every test tests/contract.md names exists", test_contract_names);
    test_run("runner: every mutant of make mutants applies once and names its failure", test_mutants_apply);
    test_run("runner: the hooks are in the runner's copy of the library alone", test_hooks_only_in_tests);
    test_run("runner: the core files stand in layers: none calls a row above (nm)", test_core_layers);
}
