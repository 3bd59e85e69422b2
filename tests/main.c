/*
** tests/main.c -- the test runner: runs every suite, prints one line per
** failed or skipped test, and ends with exactly "N passed, N failed".
**
** Usage: build/run_tests [NAME-SUBSTRING...]   (no argument: all tests)
** Environment: BRT_TEST_SEED=S replays random tests; BRT_SHARED=DIR points
** at the shared data (default ../shared, relative to the repository);
** TMPDIR is where the scratch folder goes (default /tmp); BRT_TEST_KEEP=1
** keeps it (for a failure's files).
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

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdarg.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

static int passed, failed, skipped;
static int current_failed, current_skipped;
static const char *current_name = "";
static char **filters;
static int filter_count;
static char tmpdir[512];

static int selected(const char *name)
{
    int i;
    if (filter_count == 0) return 1;
    for (i = 0; i < filter_count; i++)
        if (strstr(name, filters[i])) return 1;
    return 0;
}

void test_run(const char *name, test_fn fn)
{
    if (!selected(name)) return;
    current_name = name;
    current_failed = current_skipped = 0;
    fn();
    if (current_failed) failed++;
    else if (current_skipped) skipped++;
    else passed++;
    fflush(stdout);
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
    return tmpdir;
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
    snprintf(out, 1024, "%s/%.*s", test_tmpdir(), (int)(len - 3), name);
    if (stat(out, &st) == 0) return out;
    snprintf(cmd, sizeof cmd, "gzip -dc '%s' > '%s.part' && mv '%s.part' '%s'", src, out, out, out);
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

int main(int argc, char **argv)
{
    int keep = getenv("BRT_TEST_KEEP") != NULL;
    filters = argv + 1;
    filter_count = argc - 1;
    setvbuf(stdout, NULL, _IOLBF, 0);
    make_tmpdir(keep);
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
    suite_policy();
    suite_runner();
    if (!keep) remove_tmpdir();
    else printf("scratch files kept in %s\n", tmpdir);
    if (skipped) printf("(%d skipped, see SKIP lines above)\n", skipped);
    printf("%d passed, %d failed\n", passed, failed);
    return failed ? 1 : 0;
}
