/*
** tests/main.c -- the test runner: runs every suite, prints one line per
** failed or skipped test, and ends with exactly "N passed, N failed".
**
** Usage: build/run_tests [NAME-SUBSTRING...]   (no argument: all tests)
** Environment: BRT_TEST_SEED=S replays random tests; BRT_SHARED=DIR points
** at the shared data (default ../shared, relative to the repository);
** TMPDIR is where the scratch folder goes (default /tmp); BRT_TEST_KEEP=1
** keeps it (for a failure's files); BRT_TEST_JOBS=N runs N tests at once
** (default: one per online core; 1 runs them in this process, in order);
** BRT_TEST_TIMES=1 lists every test's seconds, slowest first, before the
** last line; BRT_TEST_FAILFAST=1 starts no test after the first failure
** (make mutants-sample: a mutant is killed by the first failure).
**
** IN PARALLEL the runner first collects the selected tests (every suite
** calls test_run, which only records), then forks N workers.  They take
** test numbers from one pipe, which the runner filled and closed: a read
** of 4 bytes from a pipe is atomic, so no test runs twice and the workers
** balance themselves.  Each worker has a scratch folder of its own
** (wK inside the runner's), so tests that name their files alike cannot
** meet.  A worker reports "started" and "ended" for each test on a second
** pipe; a test that started and never ended took its worker down (a
** crash), and is counted failed with the worker's signal.  The tests are
** queued longest first (slow_first below: so that no long test starts
** last and runs alone), then in suite order.
**
** THE SCRATCH FOLDER IS REMOVED HOWEVER THE RUNNER ENDS: a failed test, a
** crash, SIGINT, SIGTERM, even SIGKILL.  Signal handlers cannot do that
** safely (removing a tree needs opendir, which is not async-signal-safe)
** nor at all for SIGKILL, so at start the runner forks a watcher: a
** process that waits on a pipe whose only write end the runner holds
** (close-on-exec, so programs the tests start do not keep it open), and
** removes the folder when the pipe reports end of file -- when the runner
** has ended, by whatever means.  The watcher ignores the signals a
** terminal sends the whole process group (Ctrl-C), so it outlives them.
** The runner dies of its signal as it would have, exit status included.
*/
#include "test.h"
#include "testing.h"

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

static int passed, failed, skipped;
static int current_failed, current_skipped;
static const char *current_name = "";
static char **filters;
static int filter_count;
static char tmpdir[512];        /* the runner's scratch folder */
static char worker_dir[600];    /* a worker's own, inside it; "" when sequential */

/* The selected tests, collected before any runs (run_parallel). */
typedef struct { const char *name; test_fn fn; double seconds; } test_entry;
static test_entry *tests;
static int test_count, collecting, failfast;
/* Every test's name, whatever the filters (test_registered). */
static const char **all_names;
static int all_count, listing;

/* Name pieces of the slowest tests (BRT_TEST_TIMES=1 lists them), queued
** first by run_parallel so that none of them starts last. */
static const char *const slow_first[] = {
    "cli: SIGINT and SIGTERM while tracing", "svdag: end to end, shared meshes", "render: same image in every mode",
    "embree: instanced landscape", "render: shadow rays", "build: batched == direct, shared meshes",
    "bvh: crown ==", "mpi: == trace --direct", "embree: hitdiff --mesh explains every disagreement, crown",
    "bvh: fg_oahu ==", "mpi: a failed rank", "bvh: dragon ==", "svdag: grazing directions", "occlusion: batched ==",
    "threads: trace and render outputs equal", NULL
};

static int selected(const char *name)
{
    int i;
    if (filter_count == 0) return 1;
    for (i = 0; i < filter_count; i++)
        if (strstr(name, filters[i])) return 1;
    return 0;
}

static double now_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* Runs one test here; its outcome: 1 passed, 2 failed, 3 skipped.  The
** library's hooks (testing.h) start at their defaults, whatever the test
** before it in this process set and left (a CHECK returns early). */
static int run_one(const char *name, test_fn fn)
{
    current_name = name;
    current_failed = current_skipped = 0;
    brt_test_read_fault(-1, 0);
    brt_test_early_reject(1);
    brt_test_build_sizes(0, 0);
    brt_test_count_bottom(0);
    brt_test_on_batch_ray(NULL, NULL);
    fn();
    fflush(stdout);
    return current_failed ? 2 : current_skipped ? 3 : 1;
}

static void count(int outcome)
{
    if (outcome == 1) passed++;
    else if (outcome == 2) failed++;
    else skipped++;
}

void test_run(const char *name, test_fn fn)
{
    if (listing) {
        const char **grown = realloc(all_names, (size_t)(all_count + 1) * sizeof *all_names);
        if (!grown) { fprintf(stderr, "run_tests: out of memory\n"); exit(2); }
        all_names = grown;
        all_names[all_count++] = name;
        return;
    }
    if (!selected(name)) return;
    if (collecting) {
        test_entry *grown = realloc(tests, (size_t)(test_count + 1) * sizeof *tests);
        if (!grown) { fprintf(stderr, "run_tests: out of memory\n"); exit(2); }
        tests = grown;
        tests[test_count].name = name;
        tests[test_count].fn = fn;
        tests[test_count++].seconds = -1;
        return;
    }
    count(run_one(name, fn));
}

void test_fail_at(const char *file, int line, const char *fmt, ...)
{
    va_list ap;
    printf("FAIL %s: %s:%d: ", current_name, file, line);
    va_start(ap, fmt);
    vprintf(fmt, ap);
    va_end(ap);
    printf(" (seed %llu)\n", (unsigned long long)test_seed());
    current_failed = 1;
}

void test_skip(const char *fmt, ...)
{
    va_list ap;
    printf("SKIP %s: ", current_name);
    va_start(ap, fmt);
    vprintf(fmt, ap);
    va_end(ap);
    printf("\n");
    current_skipped = 1;
}

int test_failed(void) { return current_failed; }

uint64_t test_seed(void)
{
    const char *s = getenv("BRT_TEST_SEED");
    return s ? strtoull(s, NULL, 10) : 20200525u;
}

const char *test_tmpdir(void)
{
    return worker_dir[0] ? worker_dir : tmpdir;
}

const char *test_shared_mesh(const char *name)
{
    static char paths[16][1024];
    static int next;
    char src[512], cmd[4 * 1024 + 64];  /* src and three uses of out, each < 1024 */
    const char *shared = getenv("BRT_SHARED");
    char *out = paths[next++ % 16];
    size_t len = strlen(name);
    struct stat st;

    snprintf(src, sizeof src, "%s/data/meshes/%s", shared ? shared : "../shared", name);
    if (stat(src, &st) != 0) return NULL;
    if (len < 3 || strcmp(name + len - 3, ".gz") != 0) {
        snprintf(out, 1024, "%s", src);
        return out;
    }
    /* Unpack once per run with the system's gzip: the library reads no gzip. */
    /* Into the runner's folder, shared by its workers: each writes its own
    ** part file and renames it, so a reader sees a whole file or none. */
    snprintf(out, 1024, "%s/%.*s", tmpdir, (int)(len - 3), name);
    if (stat(out, &st) == 0) return out;
    snprintf(cmd, sizeof cmd, "gzip -dc '%s' > '%s.%ld' && mv '%s.%ld' '%s'", src, out, (long)getpid(), out,
             (long)getpid(), out);
    if (system(cmd) != 0) return NULL;
    return out;
}

static void remove_tmpdir(void)
{
    char cmd[600];
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmpdir);
    if (system(cmd) != 0) fprintf(stderr, "could not remove %s\n", tmpdir);
}

/* The folder in $TMPDIR, and its watcher (above).  Without a pipe or a
** process for the watcher the folder is still removed at a normal end. */
static void make_tmpdir(int keep)
{
    static const int group_signals[] = {SIGINT, SIGTERM, SIGHUP, SIGQUIT};
    const char *base = getenv("TMPDIR");
    sigset_t blocked, old;
    int fds[2];
    size_t i;
    pid_t pid;
    snprintf(tmpdir, sizeof tmpdir, "%s/batchrt-test-%ld", base && *base ? base : "/tmp", (long)getpid());
    mkdir(tmpdir, 0700);
    if (keep || pipe(fds) != 0) return;
    fflush(stdout);
    /* Blocked across the fork, so that a signal sent at once to the group
    ** cannot reach the watcher before it ignores it. */
    sigemptyset(&blocked);
    for (i = 0; i < sizeof group_signals / sizeof *group_signals; i++) sigaddset(&blocked, group_signals[i]);
    sigprocmask(SIG_BLOCK, &blocked, &old);
    pid = fork();
    if (pid == 0) {
        struct sigaction ignore;
        char byte;
        ssize_t n;
        memset(&ignore, 0, sizeof ignore);
        ignore.sa_handler = SIG_IGN;
        for (i = 0; i < sizeof group_signals / sizeof *group_signals; i++)
            sigaction(group_signals[i], &ignore, NULL);
        sigprocmask(SIG_SETMASK, &old, NULL);
        close(fds[1]);
        do n = read(fds[0], &byte, 1);
        while (n > 0 || (n < 0 && errno == EINTR));
        remove_tmpdir();        /* the runner has ended, however */
        _exit(0);
    }
    sigprocmask(SIG_SETMASK, &old, NULL);
    close(fds[0]);
    if (pid > 0) fcntl(fds[1], F_SETFD, FD_CLOEXEC);
    else close(fds[1]);
}

/* For the runner's own test (tests/test_runner.c): with
** BRT_TEST_SELFCHECK=fail|segv|int|term|abort this test leaves a file in
** the scratch folder and then fails, or dies of that signal (int: sent
** to the process group, watcher included, as a terminal's Ctrl-C is). */
static void runner_selfcheck(void)
{
    const char *mode = getenv("BRT_TEST_SELFCHECK");
    char path[600];
    FILE *f;
    snprintf(path, sizeof path, "%s/left-behind", tmpdir);
    f = fopen(path, "w");
    if (f) fclose(f);
    if (strcmp(mode, "segv") == 0) raise(SIGSEGV);
    if (strcmp(mode, "int") == 0) kill(0, SIGINT);      /* the whole group, as Ctrl-C does */
    if (strcmp(mode, "term") == 0) raise(SIGTERM);
    if (strcmp(mode, "abort") == 0) abort();
    CHECK(0, "failed on purpose (BRT_TEST_SELFCHECK=%s)", mode);
}

static void run_suites(void)
{
    if (getenv("BRT_TEST_SELFCHECK")) test_run("runner: self-check", runner_selfcheck);
    suite_mesh();
    suite_bvh();
    suite_svdag();
    suite_batched();
    suite_exchange();
    suite_faults();
    suite_mpi();
    suite_cli();
    suite_scenes();
    suite_instanced_scenes();
    suite_render();
    suite_point_size();
    suite_referee();
    suite_embree();
    suite_hardening();
    suite_build();
    suite_occlusion();
    suite_threads();
    suite_inner();
    suite_follow();
    suite_instances();
    suite_layers();
    suite_sampling();
    suite_reclaim();
    suite_pbrt();
    suite_pbrt_camera();
    suite_pbrt_state();
    suite_loopsubdiv();
    suite_policy();
    suite_reference();
    suite_entry();
    suite_thresholds();
    suite_oom();
    suite_drift();
    suite_runner();
}

int test_listing(void)
{
    return listing;
}

int test_registered(const char *name)
{
    int i;
    if (!all_names) {
        listing = 1;
        run_suites();
        listing = 0;
    }
    for (i = 0; i < all_count; i++)
        if (strcmp(all_names[i], name) == 0) return 1;
    return 0;
}

/* What a worker tells the runner: test number, 0 started / outcome, seconds. */
typedef struct { int index, what; double seconds; } report;

static void write_all(int fd, const void *data, size_t size)
{
    const char *p = data;
    while (size > 0) {
        ssize_t n = write(fd, p, size);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) _exit(3);
        p += n;
        size -= (size_t)n;
    }
}

/* A worker: takes test numbers from queue until it is empty, runs each in
** its own scratch folder, reports on results. */
static void worker(int id, int queue, int results)
{
    int index;
    snprintf(worker_dir, sizeof worker_dir, "%s/w%d", tmpdir, id);
    mkdir(worker_dir, 0700);
    while (read(queue, &index, sizeof index) == (ssize_t)sizeof index) {
        report r;
        double start = now_seconds();
        r.index = index;
        r.what = 0;
        r.seconds = 0;
        write_all(results, &r, sizeof r);
        r.what = run_one(tests[index].name, tests[index].fn);
        r.seconds = now_seconds() - start;
        write_all(results, &r, sizeof r);
    }
    _exit(0);
}

/* The queue's order: the tests slow_first names, in its order, then the rest. */
static void queue_tests(int fd)
{
    char *queued = calloc((size_t)test_count, 1);
    int i, k;
    if (!queued) { fprintf(stderr, "run_tests: out of memory\n"); exit(2); }
    for (k = 0; slow_first[k]; k++)
        for (i = 0; i < test_count; i++)
            if (!queued[i] && strstr(tests[i].name, slow_first[k])) {
                queued[i] = 1;
                write_all(fd, &i, sizeof i);
            }
    for (i = 0; i < test_count; i++)
        if (!queued[i]) write_all(fd, &i, sizeof i);
    free(queued);
}

/* Runs the collected tests in jobs workers (see the top of this file). */
static void run_parallel(int jobs)
{
    int queue[2], results[2], w, *started_by = NULL, *outcome = NULL, i, stopped = 0;
    pid_t *pids = calloc((size_t)jobs, sizeof *pids);
    report r;
    if (!pids || pipe(queue) != 0 || pipe(results) != 0) {
        fprintf(stderr, "run_tests: cannot make the workers' pipes\n");
        exit(2);
    }
    /* Filled before any worker starts, and closed: a pipe holds 16384
    ** test numbers at least, more than the suite has. */
    queue_tests(queue[1]);
    close(queue[1]);
    fcntl(queue[0], F_SETFD, FD_CLOEXEC);
    if (failfast) fcntl(queue[0], F_SETFL, fcntl(queue[0], F_GETFL) | O_NONBLOCK);
    fcntl(results[1], F_SETFD, FD_CLOEXEC);
    fflush(stdout);
    for (w = 0; w < jobs; w++) {
        pids[w] = fork();
        if (pids[w] == 0) {
            close(results[0]);
            worker(w, queue[0], results[1]);
        }
    }
    close(results[1]);
    started_by = calloc((size_t)test_count, sizeof *started_by);
    outcome = calloc((size_t)test_count, sizeof *outcome);
    if (!started_by || !outcome) { fprintf(stderr, "run_tests: out of memory\n"); exit(2); }
    for (;;) {
        ssize_t n = read(results[0], &r, sizeof r);
        if (n < 0 && errno == EINTR) continue;
        if (n != (ssize_t)sizeof r) break;
        if (r.index < 0 || r.index >= test_count) continue;
        if (r.what == 0) started_by[r.index] = 1;
        else {
            outcome[r.index] = r.what;
            tests[r.index].seconds = r.seconds;
        }
        /* Fail fast: the runner empties the queue itself, so the workers
        ** end after the tests they are running. */
        if (failfast && r.what == 2 && !stopped++)
            while (read(queue[0], &i, sizeof i) == (ssize_t)sizeof i) continue;
    }
    close(queue[0]);
    close(results[0]);
    for (w = 0; w < jobs; w++) {
        int status;
        if (pids[w] <= 0 || waitpid(pids[w], &status, 0) != pids[w]) continue;
        if (WIFSIGNALED(status))
            printf("run_tests: worker %d died of signal %d\n", w, WTERMSIG(status));
    }
    for (i = 0; i < test_count; i++) {
        if (outcome[i] == 0 && !started_by[i] && stopped) continue;   /* not run: failed fast */
        if (outcome[i] == 0) {
            printf("FAIL %s: %s\n", tests[i].name,
                   started_by[i] ? "its worker died during the test (a crash)" : "never ran: every worker ended");
            outcome[i] = 2;
        }
        count(outcome[i]);
    }
    free(started_by);
    free(outcome);
    free(pids);
}

static int slower(const void *a, const void *b)
{
    double x = ((const test_entry *)a)->seconds, y = ((const test_entry *)b)->seconds;
    return x < y ? 1 : x > y ? -1 : 0;
}

static int job_count(void)
{
    const char *s = getenv("BRT_TEST_JOBS");
    long n = s ? strtol(s, NULL, 10) : sysconf(_SC_NPROCESSORS_ONLN);
    return n < 1 ? 1 : n > 64 ? 64 : (int)n;
}

int main(int argc, char **argv)
{
    int keep = getenv("BRT_TEST_KEEP") != NULL, jobs = job_count(), i;
    filters = argv + 1;
    filter_count = argc - 1;
    failfast = getenv("BRT_TEST_FAILFAST") && *getenv("BRT_TEST_FAILFAST");
    setvbuf(stdout, NULL, _IOLBF, 0);
    make_tmpdir(keep);
    collecting = 1;
    run_suites();
    collecting = 0;
    if (jobs > test_count) jobs = test_count;
    if (jobs <= 1) {
        for (i = 0; i < test_count && !(failfast && failed); i++) {
            double start = now_seconds();
            count(run_one(tests[i].name, tests[i].fn));
            tests[i].seconds = now_seconds() - start;
        }
    } else
        run_parallel(jobs);
    if (getenv("BRT_TEST_TIMES")) {
        qsort(tests, (size_t)test_count, sizeof *tests, slower);
        for (i = 0; i < test_count; i++) printf("%8.2f s  %s\n", tests[i].seconds, tests[i].name);
    }
    free(tests);
    if (!keep) remove_tmpdir();
    else printf("scratch files kept in %s\n", tmpdir);
    if (skipped) printf("(%d skipped, see SKIP lines above)\n", skipped);
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
