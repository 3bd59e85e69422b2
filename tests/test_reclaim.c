/*
** tests/test_reclaim.c -- temporary files of killed writers are reclaimed,
** live ones never (batchrt.c, brt_atomic_open).
**
** A writer holds "path.tmp.<pid>" under an fcntl lock, which the system
** releases however the process dies; the next writer of path removes the
** unlocked ones.  The killed writer here is a child that opens its
** temporary file and then SIGKILLs itself: exactly what a build killed by
** the OOM killer leaves, without any timing.  Children leave by _exit, so
** that the runner's exit handlers run in the runner only.
*/
#include "test.h"
#include "util.h"

#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

/* A fresh folder in the scratch directory, and path NAME inside it. */
static const char *fresh_dir(const char *name)
{
    static char dir[1024];
    snprintf(dir, sizeof dir, "%s/%s", test_tmpdir(), name);
    mkdir(dir, 0755);
    return dir;
}

/* The number of entries of dir; *tmp: of them "*.tmp.*". */
static int count_entries(const char *dir, int *tmp)
{
    return tu_dir_entries(dir, ".tmp.", tmp, NULL, 0);
}

static brt_result build_into(const char *path, brt_error *err)
{
    tu_scene s;
    brt_scene_options opt;
    brt_mesh mesh;
    uint64_t st = 77;
    brt_result r;
    memset(&s, 0, sizeof s);
    tu_random_soup(&s, &st, 3000, 0.05f);
    mesh = tu_mesh_view(&s);
    memset(&opt, 0, sizeof opt);
    opt.batch_tris = 500;
    opt.proxy_res = 16;
    opt.threads = 1;
    r = brt_scene_build(&mesh, &opt, 1, path, err);
    tu_scene_free(&s);
    return r;
}

/* A child that opens path's temporary file, writes into it, and dies by
** SIGKILL: its pid, after it died. */
static pid_t killed_writer(const char *path)
{
    pid_t pid = fork();
    if (pid == 0) {
        brt_atomic_file f;
        static char junk[1 << 16];
        if (brt_atomic_open(&f, path, NULL) != BRT_OK) _exit(2);
        if (write(f.fd, junk, sizeof junk) != (ssize_t)sizeof junk) _exit(3);
        raise(SIGKILL);
        _exit(4);
    }
    if (pid > 0) {
        int status;
        waitpid(pid, &status, 0);
        if (!WIFSIGNALED(status) || WTERMSIG(status) != SIGKILL) return -1;
    }
    return pid;
}

static void test_killed_build_reclaimed(void)
{
    const char *dir = fresh_dir("reclaim-killed");
    char path[1100], stale[1200];
    brt_error err;
    struct stat st;
    pid_t a, b;
    int n, tmp;
    snprintf(path, sizeof path, "%s/scene.brs", dir);
    a = killed_writer(path);
    CHECK(a > 0, "the first writer did not die by SIGKILL");
    snprintf(stale, sizeof stale, "%s.tmp.%ld", path, (long)a);
    CHECK(stat(stale, &st) == 0 && st.st_size > 0, "a killed writer left no temporary file to reclaim");
    b = killed_writer(path);     /* the second writer reclaims the first's file, then dies too */
    CHECK(b > 0, "the second writer did not die by SIGKILL");
    EXPECT(!tu_file_exists(stale), "the second writer left the first one's temporary file");
    n = count_entries(dir, &tmp);
    CHECK(n == 1 && tmp == 1, "after two killed writers: %d files, %d temporary", n, tmp);
    CHECK(build_into(path, &err) == BRT_OK, "%s", err.message);
    n = count_entries(dir, &tmp);
    EXPECT(n == 1 && tmp == 0, "after a good build: %d files, %d of them temporary (want the scene alone)", n,
           tmp);
}

static void test_live_writer_kept(void)
{
    const char *dir = fresh_dir("reclaim-live");
    char path[1100], live[1200];
    int ready[2], go[2], status, n, tmp;
    brt_error err;
    pid_t pid;
    char byte = 0;
    snprintf(path, sizeof path, "%s/scene.brs", dir);
    CHECK(pipe(ready) == 0 && pipe(go) == 0, "pipe");
    pid = fork();
    if (pid == 0) {
        brt_atomic_file f;
        close(ready[0]);
        close(go[1]);
        if (brt_atomic_open(&f, path, NULL) != BRT_OK) _exit(2);
        if (write(ready[1], "r", 1) != 1) _exit(3);
        if (read(go[0], &byte, 1) < 0) _exit(4);      /* until the parent closes go */
        _exit(brt_atomic_close(&f, BRT_EIO, NULL) == BRT_EIO ? 0 : 5);
    }
    close(ready[1]);
    close(go[0]);
    CHECK(pid > 0 && read(ready[0], &byte, 1) == 1, "the live writer did not start");
    snprintf(live, sizeof live, "%s.tmp.%ld", path, (long)pid);
    EXPECT(build_into(path, &err) == BRT_OK, "a build beside a live writer: %s", err.message);
    EXPECT(tu_file_exists(live), "a build removed a live writer's temporary file");
    close(go[1]);
    close(ready[0]);
    waitpid(pid, &status, 0);
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 0, "the live writer failed (status %d)", status);
    n = count_entries(dir, &tmp);
    EXPECT(n == 1 && tmp == 0, "at the end: %d files, %d temporary", n, tmp);
}

static void test_concurrent_builds(void)
{
    const char *dir = fresh_dir("reclaim-two");
    char path[1100], alone[1100];
    unsigned char *a, *b;
    size_t na, nb;
    brt_error err;
    pid_t pid[2];
    int i, status, failed = 0, n, tmp;
    snprintf(path, sizeof path, "%s/scene.brs", dir);
    snprintf(alone, sizeof alone, "%s/alone.brs", test_tmpdir());
    CHECK(build_into(alone, &err) == BRT_OK, "%s", err.message);
    for (i = 0; i < 2; i++) {
        pid[i] = fork();
        if (pid[i] == 0) _exit(build_into(path, NULL) == BRT_OK ? 0 : 1);
    }
    for (i = 0; i < 2; i++) {
        if (pid[i] < 0 || waitpid(pid[i], &status, 0) != pid[i] || !WIFEXITED(status) || WEXITSTATUS(status))
            failed++;
    }
    EXPECT(failed == 0, "%d of two concurrent builds failed", failed);
    a = tu_slurp(path, &na);
    b = tu_slurp(alone, &nb);
    EXPECT(a && b && na == nb && memcmp(a, b, na) == 0, "two concurrent builds wrote other bytes than one");
    n = count_entries(dir, &tmp);
    EXPECT(n == 1 && tmp == 0, "after two concurrent builds: %d files, %d temporary", n, tmp);
    free(a);
    free(b);
}

void suite_reclaim(void)
{
    test_run("build: a killed build's temporary file is reclaimed by the next", test_killed_build_reclaimed);
    test_run("build: a live build's temporary file survives a build beside it", test_live_writer_kept);
    test_run("build: two concurrent builds both succeed, same bytes", test_concurrent_builds);
}
