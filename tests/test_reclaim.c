/*
** tests/test_reclaim.c -- temporary files of killed writers are reclaimed,
** live ones never (base.c, brt_atomic_open).
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
    opt.point_tris = 500;
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

/* ---- the reclaim rule from outside, for every program's outputs ---- */

/* Names beside OUT that only look like a temporary file of OUT: a user's
** backup, a suffix not all digits, an empty suffix, a longer or other
** base, another separator.  None may ever be touched. */
static const struct { const char *pre, *post; } lookalikes[] = {
    {"", ".tmp.backup"}, {"", ".tmp.12x"}, {"", ".tmp."}, {"", "X.tmp.123"}, {"x", ".tmp.123"},
    {"", ".bak.123"}, {"", ".tmp.123.old"}, {"", ".tmp.+123"}, {"", ".tmp. 123"}, {"", ".tmp.-123"},
    {"", ".tmp"}};
#define LOOKALIKES (sizeof lookalikes / sizeof lookalikes[0])

typedef struct planted {        /* what was put beside one output */
    char out[1200], dead[1300], live[1300];
    pid_t live_pid;
    int go;                     /* closing it lets the live writer end */
} planted;

/* A process number that no process has any more (a child that ended). */
static pid_t dead_pid(void)
{
    int status;
    pid_t pid = fork();
    if (pid == 0) _exit(0);
    if (pid > 0) waitpid(pid, &status, 0);
    return pid;
}

/* Beside out: a live writer's temporary file (a child holding it under
** its lock until p->go is closed), the unlocked file of the dead process
** number dead, and every lookalike, each holding its own name. */
static int plant(planted *p, const char *dir, const char *name, pid_t dead)
{
    int ready[2], go[2];
    char byte = 0;
    size_t i;
    snprintf(p->out, sizeof p->out, "%.1000s/%.100s", dir, name);
    if (pipe(ready) != 0 || pipe(go) != 0) return 0;
    p->live_pid = fork();
    if (p->live_pid == 0) {
        brt_atomic_file f;
        close(ready[0]);
        close(go[1]);
        if (brt_atomic_open(&f, p->out, NULL) != BRT_OK) _exit(2);
        if (write(ready[1], "r", 1) != 1) _exit(3);
        if (read(go[0], &byte, 1) < 0) _exit(4);
        _exit(brt_atomic_close(&f, BRT_EIO, NULL) == BRT_EIO ? 0 : 5);
    }
    close(ready[1]);
    close(go[0]);
    p->go = go[1];
    if (p->live_pid < 0 || read(ready[0], &byte, 1) != 1) return 0;
    close(ready[0]);
    snprintf(p->live, sizeof p->live, "%.1150s.tmp.%ld", p->out, (long)p->live_pid);
    snprintf(p->dead, sizeof p->dead, "%.1150s.tmp.%ld", p->out, (long)dead);
    if (!tu_spill(p->dead, "dead", 4)) return 0;
    for (i = 0; i < LOOKALIKES; i++) {
        char path[1400];
        snprintf(path, sizeof path, "%.1000s/%s%.100s%s", dir, lookalikes[i].pre, name, lookalikes[i].post);
        if (!tu_spill(path, path, strlen(path))) return 0;
    }
    return 1;
}

/* After the program: the dead writer's file gone, the live one's and every
** lookalike there with its bytes. */
static void check_planted(const planted *p, const char *what)
{
    size_t i;
    EXPECT(tu_file_exists(p->out), "%s: no output %s", what, p->out);
    EXPECT(!tu_file_exists(p->dead), "%s: the dead writer's %s was not reclaimed", what, p->dead);
    EXPECT(tu_file_exists(p->live), "%s: a live writer's %s was removed", what, p->live);
    for (i = 0; i < LOOKALIKES; i++) {
        char path[1400], *slash = strrchr(p->out, '/');
        unsigned char *bytes;
        size_t n;
        snprintf(path, sizeof path, "%.*s/%s%s%s", (int)(slash - p->out), p->out, lookalikes[i].pre, slash + 1,
                 lookalikes[i].post);
        bytes = tu_slurp(path, &n);
        EXPECT(bytes && n == strlen(path) && memcmp(bytes, path, n) == 0,
               "%s: the user's file %s was %s", what, path, bytes ? "changed" : "removed");
        free(bytes);
    }
}

/* Ends the live writers (all go pipes closed first: a later child holds
** copies of the earlier ones' write ends) and checks each ended cleanly. */
static void release_planted(planted *p, size_t n)
{
    size_t j;
    int status;
    for (j = 0; j < n; j++) close(p[j].go);
    for (j = 0; j < n; j++) {
        waitpid(p[j].live_pid, &status, 0);
        EXPECT(WIFEXITED(status) && WEXITSTATUS(status) == 0, "the live writer of %s failed (%d)", p[j].out,
               status);
        EXPECT(!tu_file_exists(p[j].live), "the live writer left %s", p[j].live);
    }
}

/* README, "Building scene files out of core": "Every output is written
** under NAME.tmp.PID ... every writer first removes the unlocked
** NAME.tmp.* files ... a live build's file is never touched"; and
** "Errors": every program's outputs are written so.  Reclaiming takes
** exactly NAME.tmp.<digits>: a user's NAME.tmp.backup beside the hits,
** or any name that only resembles a temporary file, is never removed.
** Checked from outside for every program that writes outputs: trace's
** hits and --stats, trace --batched's scene file, render's PNG, heat map
** and --stats, mkscene's mesh. */
static void test_programs_reclaim_only_their_own(void)
{
    static const struct { const char *args; const char *outs[3]; } runs[] = {
        {"trace @/rp/m.obj @/rp/r.rays @/rp/hits.out --stats @/rp/s.json", {"hits.out", "s.json", NULL}},
        {"trace @/rp/m.obj @/rp/r.rays @/rp/b.hits --batched --point-tris 100 --scene @/rp/sc.brs",
         {"sc.brs", "b.hits", NULL}},
        {"render @/rp/m.obj --width 8 --height 6 --spp 1 --point-tris 100 --scene @/rp/rsc.brs --out @/rp/img.png "
         "--heatmap @/rp/heat.png --stats @/rp/rs.json", {"img.png", "heat.png", "rs.json"}},
        {"mkscene crown @/rp/crown.ply --scale 0.01", {"crown.ply", NULL, NULL}}};
    const char *dir = fresh_dir("rp");
    char mesh[1100];
    tu_scene m;
    uint64_t st = 61;
    size_t k, j;
    pid_t dead = dead_pid();
    FILE *f;
    uint32_t i;
    CHECK(dead > 0, "fork");
    memset(&m, 0, sizeof m);
    tu_random_soup(&m, &st, 400, 0.1f);
    snprintf(mesh, sizeof mesh, "%s/m.obj", dir);
    f = fopen(mesh, "w");
    CHECK(f, "cannot write %s", mesh);
    for (i = 0; i < m.vcount; i++) fprintf(f, "v %.9g %.9g %.9g\n", m.pos[3 * i], m.pos[3 * i + 1], m.pos[3 * i + 2]);
    for (i = 0; i < m.tcount; i++)
        fprintf(f, "f %u %u %u\n", (unsigned)m.idx[3 * i] + 1, (unsigned)m.idx[3 * i + 1] + 1,
                (unsigned)m.idx[3 * i + 2] + 1);
    fclose(f);
    tu_scene_free(&m);
    CHECK(tu_run("raygen @/rp/m.obj @/rp/r.rays --kind random --count 300") == 0, "raygen failed");
    for (k = 0; k < sizeof runs / sizeof runs[0]; k++) {
        planted p[3];
        size_t n = 0;
        int status;
        for (j = 0; j < 3 && runs[k].outs[j]; j++, n++)
            if (!plant(&p[j], dir, runs[k].outs[j], dead)) {
                test_fail_at(__FILE__, __LINE__, "%s: cannot plant files", runs[k].outs[j]);
                release_planted(p, n);
                return;
            }
        status = tu_run("%s", runs[k].args);
        EXPECT(status == 0, "%s: exit %d: %s", runs[k].args, status, tu_last_stderr());
        for (j = 0; j < n; j++) check_planted(&p[j], runs[k].args);
        release_planted(p, n);
        if (test_failed()) return;
    }
}

void suite_reclaim(void)
{
    test_run("build: a killed build's temporary file is reclaimed by the next", test_killed_build_reclaimed);
    test_run("build: a live build's temporary file survives a build beside it", test_live_writer_kept);
    test_run("build: two concurrent builds both succeed, same bytes", test_concurrent_builds);
    test_run("reclaim: every program reclaims its own dead temporaries, never a lookalike",
             test_programs_reclaim_only_their_own);
}
