/*
** tests/test_mpi.c -- build/mpi_trace over real MPI ranks (README, "Beyond
** one machine"): its hit and occlusion files are trace --direct's, byte for
** byte, at 1 to 4 ranks (mpirun --oversubscribe on few cores), with
** proxies on and off, memory limits, both ownerships, plain and instanced
** scenes; rays crossing between ranks many times; proxies cutting the
** network bytes; and a failed rank ending the run with no output, never a
** hang.  Runs only when mpirun is on the PATH and $BRT_BUILD/mpi_trace
** exists ("make mpi"); otherwise one SKIP line.  Open MPI refuses to run
** as root unless told: the variables are set for mpirun's command line
** here, never in the user's environment.  tests/test_exchange.c checks
** the library's side without MPI.
*/
#include "test.h"
#include "util.h"

#include <math.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

/* Seconds a run may take before it counts as a hang. */
#define HANG_SECONDS 60

static const char *build_dir(void)
{
    const char *b = getenv("BRT_BUILD");
    return b ? b : "build";
}

/* Whether MPI runs can be tested; says SKIP when not. */
static int mpi_available(void)
{
    char path[1024];
    snprintf(path, sizeof path, "%s/mpi_trace", build_dir());
    if (system("command -v mpirun >/dev/null 2>&1") != 0) {
        test_skip("mpirun not found (install openmpi-bin and libopenmpi-dev, then make mpi)");
        return 0;
    }
    if (!tu_file_exists(path)) {
        test_skip("%s not found (make mpi)", path);
        return 0;
    }
    return 1;
}

/* Whether the last run's stderr shows Open MPI's launcher failing in itself
** ("ORTE_ERROR_LOG: Out of resource" on a loaded machine) rather than any
** line of our program: the run says nothing about mpi_trace. */
static int launcher_failed(void)
{
    char *err = tu_last_stderr();
    int failed = err && strstr(err, "ORTE_ERROR_LOG") && !strstr(err, "mpi_trace");
    free(err);
    return failed;
}

/* Runs "mpirun -np RANKS $BRT_BUILD/mpi_trace ARGS" ('@': the scratch
** folder) with env (NAME=VALUE words, or "") under a time limit; stdout
** and stderr to cli.out and cli.err.  Returns the exit status (124: it
** hung).  A run whose launcher failed in itself is run again, up to
** twice, saying so. */
static int mpi_run_program(const char *program, int ranks, const char *env, const char *fmt, va_list ap)
{
    char args[2048], head[1024];
    int status, attempt;
    vsnprintf(args, sizeof args, fmt, ap);
    snprintf(head, sizeof head,
             "env OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OMPI_MCA_btl=self,vader %s "
             "timeout %d mpirun --oversubscribe -np %d %s/%s ", env, HANG_SECONDS, ranks, build_dir(), program);
    for (attempt = 0;; attempt++) {
        status = tu_shell(head, args, " < /dev/null");
        if (status == 0 || attempt == 2 || !launcher_failed()) return status;
        printf("  mpi: mpirun failed in itself (ORTE_ERROR_LOG), run again: %s\n", args);
    }
}

static int last_status;          /* mpi_run's last exit status */

static int mpi_run(int ranks, const char *env, const char *fmt, ...)
{
    va_list ap;
    int status;
    va_start(ap, fmt);
    status = mpi_run_program("mpi_trace", ranks, env, fmt, ap);
    va_end(ap);
    last_status = status;
    return status;
}

/* How the last mpi_run failed: timeout's status 124 is a hang (a rank
** that waits for rays or an end that never comes). */
static const char *how_failed(void)
{
    return last_status == 124 ? "hung (ended by timeout)" : "failed";
}

/* The same with build/tests/mpi_trace_small (small thresholds). */
static int mpi_small_run(int ranks, const char *fmt, ...)
{
    va_list ap;
    int status;
    va_start(ap, fmt);
    status = mpi_run_program("tests/mpi_trace_small", ranks, "", fmt, ap);
    va_end(ap);
    return status;
}

/* A crown mesh and an instanced landscape, camera and bounce rays, and
** trace --direct's hits and occlusion bytes for each. */
static int make_inputs(void)
{
    static int made = -1;
    const char *scenes[2] = {"crown @/mpi-crown.obj --scale 0.3", "landscape @/mpi-land.pbrt --scale 0.3"};
    const char *meshes[2] = {"@/mpi-crown.obj", "@/mpi-land.pbrt"};
    const char *kinds[2] = {"camera", "bounce"};
    int m, k;
    if (made >= 0) return made;
    made = 0;
    for (m = 0; m < 2; m++) {
        if (tu_run("mkscene %s", scenes[m]) != 0) return 0;
        for (k = 0; k < 2; k++) {
            if (tu_run("raygen %s @/mpi-%d-%s.rays --kind %s --count 3000", meshes[m], m, kinds[k], kinds[k]) != 0 ||
                tu_run("trace %s @/mpi-%d-%s.rays @/mpi-%d-%s.direct", meshes[m], m, kinds[k], m, kinds[k]) != 0 ||
                tu_run("trace %s @/mpi-%d-%s.rays @/mpi-%d-%s.occ --occlusion", meshes[m], m, kinds[k], m,
                       kinds[k]) != 0)
                return 0;
        }
    }
    made = 1;
    return made;
}

/* == trace --direct at 1..4 ranks, for each scene and ray kind, with
** proxies on and off, several memory limits and both ownerships. */
static void test_equal_direct(void)
{
    const char *meshes[2] = {"@/mpi-crown.obj", "@/mpi-land.pbrt"};
    const char *kinds[2] = {"camera", "bounce"};
    int ranks, m, k;
    if (!mpi_available()) return;
    CHECK(make_inputs(), "the inputs could not be made: %s", tu_last_stderr());
    for (ranks = 1; ranks <= 4; ranks++)
        for (m = 0; m < 2; m++)
            for (k = 0; k < 2; k++) {
                int variant = ranks + 2 * m + k;   /* spreads the options over the runs */
                const char *proxy = variant % 2 ? "--no-proxy" : "";
                const char *memory = variant % 3 == 0 ? "--memory 256K" : "--memory 1G";
                const char *assign = variant % 4 >= 2 ? "round-robin" : "runs";
                int occlusion = (variant / 2) % 2;
                char out[256], ref[256];
                snprintf(out, sizeof out, "%s", tu_scratch("mpi.out"));
                snprintf(ref, sizeof ref, "%s/mpi-%d-%s.%s", test_tmpdir(), m, kinds[k],
                         occlusion ? "occ" : "direct");
                CHECK(mpi_run(ranks, "", "%s @/mpi-%d-%s.rays @/mpi.out --point-tris 2000 --proxy-res 32 "
                              "--scene @/mpi-%d.brs %s %s --assign %s %s", meshes[m], m, kinds[k], m,
                              proxy, memory, assign, occlusion ? "--occlusion" : "") == 0,
                      "%d ranks, %s %s %s: %s: %s", ranks, meshes[m], proxy, memory, how_failed(), tu_last_stderr());
                EXPECT(tu_same_file_bytes(out, ref), "%d ranks, %s, %s rays, %s %s %s%s: differs from trace --direct",
                       ranks, meshes[m], kinds[k], proxy, memory, assign, occlusion ? ", occlusion" : "");
            }
}

/* A corridor: 200 triangles across the x axis, each filling half of its
** box, and a wall at the end.  Rays along x pass through every box and
** hit only the wall.  With one triangle per batching point dealt round
** robin to 4 ranks, each ray is sent on at nearly every box without
** proxies; the proxies see that it misses the triangles. */
static int write_corridor(const char *obj, const char *rays_path)
{
    FILE *f = fopen(obj, "w");
    brt_ray rays[500];
    brt_error err;
    int i;
    if (!f) return 0;
    for (i = 0; i < 200; i++) fprintf(f, "v %d 0 -1\nv %d 1 -1\nv %d 1 1\nf -3 -2 -1\n", i, i, i);
    fprintf(f, "v 200 0 -1\nv 200 1 -1\nv 200 1 1\nv 200 0 1\nf -4 -3 -2 -1\n");
    fclose(f);
    for (i = 0; i < 500; i++) {
        brt_ray *r = &rays[i];
        r->org[0] = -1.0f;
        r->org[1] = 0.15f + 0.001f * (float)i;    /* y in [0.15, 0.65) */
        r->org[2] = 0.7f + 0.0005f * (float)i;    /* above the triangles' diagonal */
        r->dir[0] = 1.0f;
        r->dir[1] = r->dir[2] = 0.0f;
        r->tnear = 0.0f;
        r->tfar = INFINITY;
    }
    return brt_rays_write(rays_path, rays, 500, &err) == BRT_OK;
}

static void test_crossings_and_proxies(void)
{
    const char *stats = tu_scratch("mpi-cross.json");
    double sent[2], bytes[2], rays = 0;
    int proxies;
    if (!mpi_available()) return;
    CHECK(write_corridor(tu_scratch("corridor.obj"), tu_scratch("corridor.rays")), "corridor");
    CHECK(tu_run("trace @/corridor.obj @/corridor.rays @/corridor.direct") == 0, "trace --direct");
    for (proxies = 0; proxies < 2; proxies++) {
        CHECK(mpi_run(4, "", "@/corridor.obj @/corridor.rays @/mpi.out --point-tris 1 --proxy-res 32 "
                      "--scene @/corridor.brs --assign round-robin --stats @/mpi-cross.json %s",
                      proxies ? "" : "--no-proxy") == 0,
              "%s: %s", how_failed(), tu_last_stderr());
        EXPECT(tu_same_file_bytes(tu_scratch("mpi.out"), tu_scratch("corridor.direct")), "hits differ");
        sent[proxies] = tu_json_file_number(stats, "rays_sent");
        bytes[proxies] = tu_json_file_number(stats, "bytes_sent");
        rays = tu_json_file_number(stats, "rays_started");
        EXPECT(tu_json_file_number(stats, "rays_finished") == rays && rays == 500,
               "started %.0f, finished %.0f", rays, tu_json_file_number(stats, "rays_finished"));
        EXPECT(tu_json_file_number(stats, "rays_received") == sent[proxies], "sent != received");
    }
    EXPECT(sent[0] >= 100 * rays, "without proxies only %.0f rays sent for %.0f", sent[0], rays);
    EXPECT(bytes[1] < bytes[0] / 10, "proxies did not cut the bytes sent: %.0f with, %.0f without",
           bytes[1], bytes[0]);
}

/* The last run's stderr has exactly one line of mpi_trace's, holding what. */
static void expect_one_line(const char *when, const char *what)
{
    char *err = tu_last_stderr();
    const char *p = err;
    int lines = 0;
    while (p && (p = strstr(p, "mpi_trace: ")) != NULL) {
        lines++;
        p++;
    }
    EXPECT(lines == 1 && strstr(err, what), "%s: %d lines of mpi_trace's, want one with '%s': %s", when,
           lines, what, err ? err : "");
    free(err);
}

/* A failed rank -- at open, at a send, killed by a signal -- ends the run
** with a non-zero status and no output file, within the time limit. */
static void test_failures(void)
{
    const char *when[3] = {"open", "send", "signal"};
    int i, status;
    if (!mpi_available()) return;
    CHECK(make_inputs(), "the inputs could not be made");
    for (i = 0; i < 3; i++) {
        char env[64];
        remove(tu_scratch("mpi-fail.out"));
        snprintf(env, sizeof env, "BRT_MPI_FAIL=1:%s", when[i]);
        status = mpi_run(3, env, "@/mpi-crown.obj @/mpi-0-bounce.rays @/mpi-fail.out --point-tris 50 "
                         "--proxy-res 32 --scene @/mpi-50.brs --assign round-robin --no-proxy");
        EXPECT(status != 0 && status != 124, "%s: exit status %d", when[i], status);
        EXPECT(!tu_file_exists(tu_scratch("mpi-fail.out")), "%s: an output file was left", when[i]);
        EXPECT(!tu_temporary_file_left(), "%s: a temporary file was left", when[i]);
        if (i < 2) expect_one_line(when[i], "mpi_trace: rank 1: ");
    }
    status = mpi_run(2, "", "@/mpi-crown.obj @/missing.rays @/mpi-fail.out --scene @/mpi-50.brs");
    EXPECT(status == 1 && !tu_file_exists(tu_scratch("mpi-fail.out")), "missing rays: status %d", status);
    expect_one_line("missing rays", "missing.rays");
    status = mpi_run(3, "", "@/mpi-crown.obj @/mpi-0-bounce.rays @/mpi-fail.out --assign diagonal");
    EXPECT(status == 1 && !tu_file_exists(tu_scratch("mpi-fail.out")), "bad option: status %d", status);
    expect_one_line("a bad option", "--assign: expected runs or round-robin, got 'diagonal'");
}

/* Rank 0 prepares the scene file from the mesh with the options given
** (README, "Beyond one machine"): the bytes trace --batched builds with the
** same --proxy-res and --point-tris, at two resolutions (a proxy resolution
** dropped would give the default's file, and the same hits). */
static void test_builds_trace_scene(void)
{
    const char *res[2] = {"16", "64"};
    int i;
    if (!mpi_available()) return;
    CHECK(make_inputs(), "the inputs could not be made");
    for (i = 0; i < 2; i++) {
        CHECK(tu_run("trace @/mpi-crown.obj @/mpi-0-bounce.rays @/res-t.hits --batched --proxy-res %s --point-tris 50 "
                     "--scene @/res-t.brs", res[i]) == 0, "trace --batched failed");
        EXPECT(mpi_run(1, "", "@/mpi-crown.obj @/mpi-0-bounce.rays @/res-m.hits --proxy-res %s --point-tris 50 "
                       "--scene @/res-m.brs", res[i]) == 0, "--proxy-res %s: mpi_trace %s", res[i], how_failed());
        EXPECT(tu_same_file_bytes(tu_scratch("res-t.brs"), tu_scratch("res-m.brs")),
               "--proxy-res %s: mpi_trace's scene file is not trace's", res[i]);
        remove(tu_scratch("res-t.brs"));
        remove(tu_scratch("res-m.brs"));
    }
}

/* README, "Errors": SIGINT stops a build and leaves nothing.  Rank 0's
** scene build (of a mesh that takes about a second) is interrupted as soon
** as its temporary file appears: it must stop it
** (brt_scene_options.interrupt), leave no scene file, temporary or whole,
** and no output, and end with a failure, never hang.  mpi_trace runs as an
** MPI singleton (no mpirun) and the signal goes to it alone: through
** mpirun, whether and when a rank sees it depends on Open MPI (its SIGTERM,
** then SIGKILL after a grace of one second), not on batchrt. */
static void test_interrupted_build(void)
{
    char command[2048], dir[512], left[256] = "";
    long waited = 0;
    int status = 0, entries;
    pid_t pid;
    if (!mpi_available()) return;
    CHECK(tu_run("mkscene landscape @/mpi-int.ply --scale 0.15625") == 0 &&
          tu_run("raygen @/mpi-int.ply @/mpi-int.rays --kind random --count 1000") == 0, "cannot make the inputs");
    snprintf(dir, sizeof dir, "%s", tu_scratch("mpi-int"));
    CHECK(mkdir(dir, 0755) == 0, "cannot create %s", dir);
    tu_expand_scratch("exec env OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OMPI_MCA_btl=self,vader "
                      "$BRT_BUILD/mpi_trace @/mpi-int.ply @/mpi-int.rays @/mpi-int.out "
                      "--scene @/mpi-int/scene.brs < /dev/null > /dev/null 2>&1", command, sizeof command);
    pid = fork();
    if (pid == 0) {
        setpgid(0, 0);
        setenv("BRT_BUILD", build_dir(), 1);
        execl("/bin/sh", "sh", "-c", command, (char *)NULL);
        _exit(127);
    }
    CHECK(pid > 0, "cannot start mpirun");
    setpgid(pid, pid);   /* either side may come first */
    while (waited < HANG_SECONDS * 1000 && tu_dir_entries(dir, NULL, NULL, NULL, 0) == 0 &&
           waitpid(pid, &status, WNOHANG) == 0) {
        tu_sleep_ms(10);
        waited += 10;
    }
    EXPECT(tu_dir_entries(dir, NULL, NULL, NULL, 0) > 0, "the build never began");
    kill(pid, SIGINT);
    for (waited = 0; waited < HANG_SECONDS * 1000 && waitpid(pid, &status, WNOHANG) == 0; waited += 10)
        tu_sleep_ms(10);
    if (waited >= HANG_SECONDS * 1000) {
        kill(-pid, SIGKILL);
        waitpid(pid, &status, 0);
        EXPECT(0, "the interrupted run hung");
    }
    EXPECT(WIFEXITED(status) && WEXITSTATUS(status) != 0, "the interrupted run: status %#x", (unsigned)status);
    entries = tu_dir_entries(dir, NULL, NULL, left, sizeof left);
    EXPECT(entries == 0, "the interrupted build left %d files, e.g. '%s'", entries, left);
    EXPECT(!tu_file_exists(tu_scratch("mpi-int.out")), "the interrupted run wrote its output");
}

/* ==== issue 38: the contract's statements, each pinned ====================
** The scene for the tests below: CLUSTERS squares of GRID x GRID unit
** quads (2 GRID^2 triangles each) in the plane z = 0, at x = 0, 100, 200,
** 300, built with --point-tris 2 GRID^2, so that each square is one
** batching point (checked against trace's own statistics) and the
** top-level leaf order runs along x (one way or the other).  A ray
** "at square c" starts above it and goes straight down: it enters no
** other square's box, so it visits exactly one batching point and
** finishes on the rank owning that square.  That makes who starts,
** sends, receives and finishes each ray known from the ray file alone
** (the independent model), whatever direction the leaf order runs: the
** ray files below are built so that every count holds both ways. */
#define CLUSTERS 4
#define GRID 8
#define RAY_BYTES 88        /* sizeof(brt_ray_state), README: "an 88-byte brt_ray_state" */
#define RAYS_PER_MESSAGE 4096   /* README: "at most 4096 (352 KiB)" */
#define SMALL_RESULTS 1000  /* the Makefile's MPI_SMALL_RESULTS */

static int write_squares(const char *obj)
{
    FILE *f = fopen(obj, "w");
    int c, i, j;
    if (!f) return 0;
    for (c = 0; c < CLUSTERS; c++)
        for (i = 0; i < GRID; i++)
            for (j = 0; j < GRID; j++) {
                float x = 100.0f * (float)c + (float)i, y = (float)j;
                fprintf(f, "v %g %g 0\nv %g %g 0\nv %g %g 0\nv %g %g 0\nf -4 -3 -2\nf -4 -2 -1\n", x, y,
                        x + 1, y, x + 1, y + 1, x, y + 1);
            }
    fclose(f);
    return 1;
}

/* A ray file: segments of (square, number of rays) in order; each ray at a
** point of its own (a low-discrepancy sequence), so every hit differs. */
static int write_square_rays(const char *path, const int *plan, int segments)
{
    size_t total = 0, n = 0;
    brt_ray *rays;
    brt_error err;
    int seg, ok;
    for (seg = 0; seg < segments; seg++) total += (size_t)plan[2 * seg + 1];
    rays = malloc((total ? total : 1) * sizeof *rays);
    if (!rays) return 0;
    for (seg = 0; seg < segments; seg++) {
        int i;
        for (i = 0; i < plan[2 * seg + 1]; i++, n++) {
            brt_ray *r = &rays[n];
            double u = fmod(0.5 + (double)n * 0.6180339887498949, 1.0);
            double v = fmod(0.5 + (double)n * 0.7548776662466927, 1.0);
            r->org[0] = 100.0f * (float)plan[2 * seg] + 0.01f + (float)(u * (GRID - 0.02));
            r->org[1] = 0.01f + (float)(v * (GRID - 0.02));
            r->org[2] = 1.0f;
            r->dir[0] = r->dir[1] = 0.0f;
            r->dir[2] = -1.0f;
            r->tnear = 0.0f;
            r->tfar = INFINITY;
        }
    }
    ok = brt_rays_write(path, rays, total, &err) == BRT_OK;
    free(rays);
    return ok;
}

/* The squares' scene file, made once by trace --batched; its statistics
** must count one batching point per square. */
static int make_squares(void)
{
    static int made = -1;
    const int plan[2] = {0, 1};
    double points;
    if (made >= 0) return made;
    made = 0;
    if (!write_squares(tu_scratch("sq.obj")) || !write_square_rays(tu_scratch("sq.rays"), plan, 1) ||
        tu_run("trace @/sq.obj @/sq.rays @/sq.tmp --batched --point-tris %d --proxy-res 16 --scene @/sq.brs "
               "--stats @/sq-build.json", 2 * GRID * GRID) != 0)
        return 0;
    points = tu_json_file_number(tu_scratch("sq-build.json"), "batching_points");
    EXPECT(points == CLUSTERS, "the squares make %.0f batching points, want %d", points, CLUSTERS);
    made = points == CLUSTERS;
    return made;
}

/* Writes plan's rays to sq.rays and trace --direct's hits to sq.direct. */
static int square_rays(const int *plan, int segments)
{
    return write_square_rays(tu_scratch("sq.rays"), plan, segments) &&
           tu_run("trace @/sq.obj @/sq.rays @/sq.direct --direct") == 0;
}

/* A figure of a statistics JSON: of per_rank[rank], or (rank -1) the total. */
static double stat_of(const char *json, int rank, const char *name)
{
    const char *p = json ? strstr(json, rank < 0 ? "\"total\"" : "\"per_rank\"") : NULL;
    int k;
    if (!p) return NAN;
    for (k = 0; k <= rank; k++)
        if (!(p = strchr(p + 1, '{'))) return NAN;
    return tu_json_number(p, name);
}

static const char *const stat_fields[15] = {
    "rays_started", "rays_finished", "rays_sent", "rays_received", "messages_sent", "bytes_sent",
    "batch_loads", "prototype_loads", "disk_bytes_read", "proxy_tests", "proxy_culled",
    "queued_visits", "resident_visits", "peak_rss_bytes", "trace_microseconds"};

/* README: "`total` and one object per rank in `per_rank`": every figure of
** the total is the sum of the ranks' (each rank's object its own: a copy
** of one rank's everywhere breaks the sums wherever ranks differ), and
** every rank's object has every field. */
static void expect_sums(const char *json, int ranks, const char *what)
{
    int f, k;
    for (f = 0; f < 15; f++) {
        double sum = 0, total = stat_of(json, -1, stat_fields[f]);
        for (k = 0; k < ranks; k++) {
            double v = stat_of(json, k, stat_fields[f]);
            EXPECT(v == v, "%s: per_rank[%d] has no %s", what, k, stat_fields[f]);
            sum += v;
        }
        EXPECT(sum == total, "%s: %s: total %.0f, sum over ranks %.0f", what, stat_fields[f], total, sum);
    }
    EXPECT(stat_of(json, ranks, "rays_started") != stat_of(json, ranks, "rays_started"),
           "%s: more than %d objects in per_rank", what, ranks);
}

/* The messages rank k sent that carried rays, from its figures: the run's
** other messages are the idle ranks' reports to rank 0 (8 bytes each:
** README, "idle ranks report their finished rays to rank 0") and rank 0's
** end of the run to each other rank (no bytes).  Also checks that the
** bytes are what those messages carry: 88 per ray, 8 per report. */
static double ray_messages(const char *json, int k, int ranks, const char *what)
{
    double sent = stat_of(json, k, "rays_sent"), bytes = stat_of(json, k, "bytes_sent");
    double reports = (bytes - RAY_BYTES * sent) / 8;
    EXPECT(reports >= 0 && reports == floor(reports), "%s: rank %d: %.0f bytes for %.0f rays", what, k, bytes,
           sent);
    if (k == 0) EXPECT(reports == 0, "%s: rank 0 sent %.0f bytes for %.0f rays", what, bytes, sent);
    else if (stat_of(json, k, "rays_finished") > 0)
        EXPECT(reports >= 1, "%s: rank %d finished rays and never reported them", what, k);
    return stat_of(json, k, "messages_sent") - reports - (k == 0 ? ranks - 1 : 0);
}

/* README: "Messages: the rays one batch sends to one rank, at most 4096".
** Two ranks, round-robin, the ray file [S at A, S at B, S at A, S at B]
** (squares A, B neighbours): each rank starts 2S rays and owns one of A, B,
** so it
** sends S rays in its first batch, in ceil(S / 4096) messages -- at S =
** 4095, 4096, 4097 and 8193: one before, at and past the limit, and past
** twice.  The shipped binary: the limit is its own. */
static void test_ray_messages(void)
{
    const int sizes[4] = {4095, 4096, 4097, 8193};
    int i, k;
    if (!mpi_available()) return;
    CHECK(make_squares(), "the squares: %s", tu_last_stderr());
    for (i = 0; i < 4; i++) {
        int S = sizes[i], plan[8] = {0, 0, 1, 0, 0, 0, 1, 0};
        char *json;
        plan[1] = plan[3] = plan[5] = plan[7] = S;
        CHECK(square_rays(plan, 4), "rays: %s", tu_last_stderr());
        CHECK(mpi_run(2, "", "@/sq.brs @/sq.rays @/mpi.out --stats @/sq.json --assign round-robin") == 0,
              "S %d: %s", S,
              tu_last_stderr());
        EXPECT(tu_same_file_bytes(tu_scratch("mpi.out"), tu_scratch("sq.direct")), "S %d: hits differ", S);
        json = (char *)tu_slurp(tu_scratch("sq.json"), NULL);
        for (k = 0; k < 2; k++) {
            double want = (double)((S + RAYS_PER_MESSAGE - 1) / RAYS_PER_MESSAGE);
            double got = ray_messages(json, k, 2, "messages");
            EXPECT(stat_of(json, k, "rays_sent") == S && stat_of(json, k, "rays_received") == S,
                   "S %d: rank %d sent %.0f, received %.0f", S, k, stat_of(json, k, "rays_sent"),
                   stat_of(json, k, "rays_received"));
            EXPECT(got == want, "S %d: rank %d sent %.0f messages of rays, want %.0f", S, k, got, want);
        }
        free(json);
    }
}

/* README: "rank 0 gathers the hits in ray order": the other ranks' hits
** travel in chunks (2^20 results; 1000 in build/tests/mpi_trace_small,
** the same code with the Makefile's MPI_SMALL_RESULTS).  Two ranks,
** round-robin (neighbours A and B on different ranks), the ray file [a at A, b at B | c at A, d at B] with a + c = b + d = T: rank
** 1 finishes exactly T rays whichever square it owns; T = 999, 1000,
** 1001, 2000, 2001 (one before, at, past one chunk and two).  Each hit
** file == trace --direct's, and rank 1's rays_finished is T. */
static void test_result_chunks(void)
{
    const int totals[5] = {999, 1000, 1001, 2000, 2001};
    char small[1024];
    int i;
    if (!mpi_available()) return;
    snprintf(small, sizeof small, "%s/tests/mpi_trace_small", build_dir());
    if (!tu_file_exists(small)) {
        test_skip("%s not found (make mpi)", small);
        return;
    }
    CHECK(make_squares(), "the squares: %s", tu_last_stderr());
    for (i = 0; i < 5; i++) {
        int T = totals[i], plan[8] = {0, 0, 1, 0, 0, 0, 1, 0};
        char *json;
        plan[1] = (T + 1) / 2;
        plan[3] = T / 2;
        plan[5] = T / 2;
        plan[7] = (T + 1) / 2;
        CHECK(square_rays(plan, 4), "rays: %s", tu_last_stderr());
        CHECK(mpi_small_run(2, "@/sq.brs @/sq.rays @/mpi.out --stats @/sq.json --assign round-robin") == 0,
              "T %d: %s", T,
              tu_last_stderr());
        EXPECT(tu_same_file_bytes(tu_scratch("mpi.out"), tu_scratch("sq.direct")),
               "T %d (chunks of %d): hits differ from trace --direct", T, SMALL_RESULTS);
        json = (char *)tu_slurp(tu_scratch("sq.json"), NULL);
        EXPECT(stat_of(json, 1, "rays_finished") == T, "T %d: rank 1 finished %.0f rays", T,
               stat_of(json, 1, "rays_finished"));
        free(json);
    }
}
/* Runs mpi_trace over the squares (ranks, options) with --stats sq.json;
** its hits must be trace --direct's; returns the JSON (malloc'd) or NULL. */
static char *squares_run(int ranks, const char *options, const char *what)
{
    if (mpi_run(ranks, "", "@/sq.brs @/sq.rays @/mpi.out --stats @/sq.json %s", options) != 0) {
        EXPECT(0, "%s: failed: %s", what, tu_last_stderr());
        return NULL;
    }
    EXPECT(tu_same_file_bytes(tu_scratch("mpi.out"), tu_scratch("sq.direct")), "%s: hits differ", what);
    return (char *)tu_slurp(tu_scratch("sq.json"), NULL);
}

/* Every per-rank figure against the model of the squares (the header
** comment above), at 3, 2 and 1 ranks, both ownerships, proxies on and
** off -- README, "Statistics", "each rank ... owns the batching points
** brt_scene_assign gives it: runs of the top-level leaf order ...
** (--assign round-robin: point k to rank k mod N), whose blobs alone it
** reads", "It starts its share of the rays" (a contiguous range, as even
** as can be), "the proxies are always consulted". */
static void test_statistics(void)
{
    const int P = 200, Q = 150;
    int plan[8] = {0, 0, 1, 0, 2, 0, 3, 0}, pair[8] = {0, 0, 1, 0, 0, 0, 1, 0};
    double one_disk, one_loads, f0, f1;
    char *json;
    int k;
    if (!mpi_available()) return;
    CHECK(make_squares(), "the squares: %s", tu_last_stderr());

    /* 3 ranks, round-robin, [P at 0, Q at 1, Q at 2, P at 3] (700 rays:
    ** shares 233, 233, 234).  The leaf order 0 1 2 3 or 3 2 1 0 deals
    ** squares 0 and 3 to rank 0 either way, 1 and 2 to ranks 1 and 2. */
    plan[1] = plan[7] = P;
    plan[3] = plan[5] = Q;
    CHECK(square_rays(plan, 4), "rays: %s", tu_last_stderr());
    CHECK(tu_run("trace @/sq.obj @/sq.rays @/sq.one --batched --point-tris %d --proxy-res 16 --scene @/sq.brs "
                 "--stats @/sq-one.json", 2 * GRID * GRID) == 0,
          "trace --batched: %s", tu_last_stderr());
    one_disk = tu_json_file_number(tu_scratch("sq-one.json"), "disk_bytes_read");
    one_loads = tu_json_file_number(tu_scratch("sq-one.json"), "batch_loads");
    json = squares_run(3, "--assign round-robin", "3 ranks, round-robin");
    CHECK(json, "no statistics");
    expect_sums(json, 3, "3 ranks");
    EXPECT(tu_json_number(json, "ranks") == 3 && tu_json_number(json, "proxies") == 1 &&
           strstr(json, "\"assign\": \"round-robin\""), "3 ranks: the run's fields: %s", json);
    for (k = 0; k < 3; k++) {
        double started = stat_of(json, k, "rays_started"), finished = stat_of(json, k, "rays_finished");
        double share = (double)(700 * (k + 1) / 3 - 700 * k / 3);
        double want_finished = k == 0 ? 2 * P : Q, want_loads = k == 0 ? 2 : 1;
        EXPECT(started == share, "3 ranks: rank %d started %.0f rays, its share is %.0f", k, started, share);
        EXPECT(finished == want_finished, "3 ranks: rank %d finished %.0f, its squares hold %.0f", k, finished,
               want_finished);
        /* each ray visits one point: started here and kept, or received */
        EXPECT(started - stat_of(json, k, "rays_sent") + stat_of(json, k, "rays_received") == finished,
               "3 ranks: rank %d: started %.0f - sent %.0f + received %.0f != finished %.0f", k, started,
               stat_of(json, k, "rays_sent"), stat_of(json, k, "rays_received"), finished);
        EXPECT(stat_of(json, k, "batch_loads") == want_loads, "3 ranks: rank %d loaded %.0f points, owns %.0f", k,
               stat_of(json, k, "batch_loads"), want_loads);
        EXPECT(stat_of(json, k, "proxy_tests") >= started && stat_of(json, k, "proxy_culled") == 0,
               "3 ranks: rank %d: %.0f proxy tests (%.0f culled) for %.0f rays started", k,
               stat_of(json, k, "proxy_tests"), stat_of(json, k, "proxy_culled"), started);
        EXPECT(stat_of(json, k, "queued_visits") + stat_of(json, k, "resident_visits") == finished,
               "3 ranks: rank %d: %.0f + %.0f visits for %.0f rays of one visit each", k,
               stat_of(json, k, "queued_visits"), stat_of(json, k, "resident_visits"), finished);
        EXPECT(stat_of(json, k, "peak_rss_bytes") > 0 && stat_of(json, k, "trace_microseconds") > 0,
               "3 ranks: rank %d: no memory or time", k);
        ray_messages(json, k, 3, "3 ranks");
    }
    EXPECT(tu_json_number(json, "disk_bytes_read") == one_disk && tu_json_number(json, "batch_loads") == one_loads,
           "3 ranks read %.0f bytes in %.0f loads, one process %.0f in %.0f: a rank read a blob it does not own",
           tu_json_number(json, "disk_bytes_read"), tu_json_number(json, "batch_loads"), one_disk, one_loads);
    EXPECT(stat_of(json, 0, "disk_bytes_read") > stat_of(json, 1, "disk_bytes_read"),
           "3 ranks: rank 0 loads two points, rank 1 one: %.0f, %.0f bytes", stat_of(json, 0, "disk_bytes_read"),
           stat_of(json, 1, "disk_bytes_read"));
    free(json);

    /* 2 ranks, [P at 0, Q at 1 | P at 0, Q at 1]: runs keep neighbours 0
    ** and 1 on one rank (the other finishes nothing and loads nothing);
    ** round-robin deals them to both.  Proxies off: no proxy test. */
    pair[1] = pair[5] = P;
    pair[3] = pair[7] = Q;
    CHECK(square_rays(pair, 4), "rays: %s", tu_last_stderr());
    json = squares_run(2, "--assign runs --no-proxy", "2 ranks, runs");
    CHECK(json, "no statistics");
    expect_sums(json, 2, "2 ranks, runs");
    EXPECT(tu_json_number(json, "ranks") == 2 && tu_json_number(json, "proxies") == 0 &&
           strstr(json, "\"assign\": \"runs\""), "2 ranks: the run's fields: %s", json);
    f0 = stat_of(json, 0, "rays_finished");
    f1 = stat_of(json, 1, "rays_finished");
    EXPECT((f0 == 0 || f1 == 0) && f0 + f1 == 2 * (P + Q), "runs: ranks finished %.0f and %.0f", f0, f1);
    for (k = 0; k < 2; k++) {
        int idle = stat_of(json, k, "rays_finished") == 0;
        EXPECT(stat_of(json, k, "rays_started") == P + Q, "runs: rank %d started %.0f", k,
               stat_of(json, k, "rays_started"));
        EXPECT(stat_of(json, k, "proxy_tests") == 0, "--no-proxy: rank %d made %.0f proxy tests", k,
               stat_of(json, k, "proxy_tests"));
        EXPECT(stat_of(json, k, "batch_loads") == (idle ? 0 : 2) &&
               (stat_of(json, k, "disk_bytes_read") == 0) == idle,
               "runs: rank %d (%s) loaded %.0f points, %.0f bytes", k, idle ? "owning no ray's point" : "owning both",
               stat_of(json, k, "batch_loads"), stat_of(json, k, "disk_bytes_read"));
        EXPECT(stat_of(json, k, "rays_sent") == (idle ? P + Q : 0) &&
               stat_of(json, k, "rays_received") == (idle ? 0 : P + Q),
               "runs: rank %d sent %.0f, received %.0f", k, stat_of(json, k, "rays_sent"),
               stat_of(json, k, "rays_received"));
        ray_messages(json, k, 2, "2 ranks, runs");
    }
    free(json);
    json = squares_run(2, "--assign round-robin", "2 ranks, round-robin");
    CHECK(json, "no statistics");
    expect_sums(json, 2, "2 ranks, round-robin");
    f0 = stat_of(json, 0, "rays_finished");
    f1 = stat_of(json, 1, "rays_finished");
    EXPECT((f0 == 2 * P && f1 == 2 * Q) || (f0 == 2 * Q && f1 == 2 * P), "round-robin: ranks finished %.0f and %.0f",
           f0, f1);
    for (k = 0; k < 2; k++)
        EXPECT(stat_of(json, k, "rays_sent") == (stat_of(json, k, "rays_finished") == 2 * P ? Q : P),
               "round-robin: rank %d sent %.0f", k, stat_of(json, k, "rays_sent"));
    free(json);

    /* 1 rank: no message at all, every ray started and finished there. */
    json = squares_run(1, "", "1 rank");
    CHECK(json, "no statistics");
    expect_sums(json, 1, "1 rank");
    EXPECT(stat_of(json, 0, "rays_started") == 2 * (P + Q) && stat_of(json, 0, "rays_finished") == 2 * (P + Q) &&
           stat_of(json, 0, "rays_sent") == 0 && stat_of(json, 0, "rays_received") == 0 &&
           stat_of(json, 0, "messages_sent") == 0 && stat_of(json, 0, "bytes_sent") == 0 &&
           stat_of(json, 0, "batch_loads") == 2, "1 rank: %s", json);
    free(json);
}

/* README, "Failures": "Rank 0 writes only at the end: a failed run leaves
** no file" -- also when the second file (--stats) fails after the hits
** were written, and when the failing rank is rank 0 or the last one (the
** line names it).  "--rays-in-flight N" takes 1 (a boundary: each
** arrival waits for a free slot) but not 0. */
static void test_failure_paths(void)
{
    const int plan[8] = {0, 150, 1, 150, 0, 150, 1, 150};
    int status;
    if (!mpi_available()) return;
    CHECK(make_squares(), "the squares: %s", tu_last_stderr());
    CHECK(square_rays(plan, 4), "rays: %s", tu_last_stderr());
    remove(tu_scratch("mpi.out"));
    status = mpi_run(2, "", "@/sq.brs @/sq.rays @/mpi.out --stats @/no/such/folder/s.json");
    EXPECT(status != 0 && status != 124, "a --stats that cannot be written: status %d", status);
    EXPECT(!tu_file_exists(tu_scratch("mpi.out")), "a failed --stats left the hit file");
    EXPECT(!tu_temporary_file_left(), "a failed --stats left a temporary file");
    remove(tu_scratch("mpi.out"));
    status = mpi_run(2, "BRT_MPI_FAIL=0:send", "@/sq.brs @/sq.rays @/mpi.out --assign round-robin");
    EXPECT(status != 0 && status != 124 && !tu_file_exists(tu_scratch("mpi.out")), "rank 0 failed: status %d",
           status);
    expect_one_line("rank 0's send", "mpi_trace: rank 0: ");
    remove(tu_scratch("mpi.out"));
    status = mpi_run(3, "BRT_MPI_FAIL=2:open", "@/sq.brs @/sq.rays @/mpi.out");
    EXPECT(status == 1 && !tu_file_exists(tu_scratch("mpi.out")), "rank 2 failed to open: status %d", status);
    expect_one_line("rank 2's open", "mpi_trace: rank 2: ");
    remove(tu_scratch("mpi.out"));
    status = mpi_run(2, "", "@/sq.brs @/sq.rays @/mpi.out --rays-in-flight 0");
    EXPECT(status == 1 && !tu_file_exists(tu_scratch("mpi.out")), "--rays-in-flight 0: status %d", status);
    expect_one_line("--rays-in-flight 0", "--rays-in-flight");
    CHECK(tu_run("trace @/sq.obj @/sq.rays @/sq.direct --direct") == 0, "trace --direct");
    status = mpi_run(2, "", "@/sq.brs @/sq.rays @/mpi.out --rays-in-flight 1 --occlusion");
    CHECK(tu_run("trace @/sq.obj @/sq.rays @/sq.occ --direct --occlusion") == 0, "trace --direct --occlusion");
    EXPECT(status == 0 && tu_same_file_bytes(tu_scratch("mpi.out"), tu_scratch("sq.occ")),
           "--rays-in-flight 1 --occlusion: status %d, or the bytes differ from trace --direct's", status);
}

/* make test-long (BRT_TEST_LONG=1): the shipped binary past its chunk of
** 2^20 results: rank 1 finishes 2^20 + 1 rays ([a at A, b at B | c at A,
** d at B], a + c = b + d), and the hits are trace --direct's. */
static void test_long_results(void)
{
    const int T = (1 << 20) + 1;
    int plan[8] = {0, 0, 1, 0, 0, 0, 1, 0};
    char *json;
    if (!getenv("BRT_TEST_LONG")) {
        test_skip("a long test: make test-long");
        return;
    }
    if (!mpi_available()) return;
    CHECK(make_squares(), "the squares: %s", tu_last_stderr());
    plan[1] = (T + 1) / 2;
    plan[3] = T / 2;
    plan[5] = T / 2;
    plan[7] = (T + 1) / 2;
    CHECK(square_rays(plan, 4), "rays: %s", tu_last_stderr());
    json = squares_run(2, "--assign round-robin", "2^20 + 1 results on rank 1");
    CHECK(json, "no statistics");
    EXPECT(stat_of(json, 1, "rays_finished") == T, "rank 1 finished %.0f rays, want %d",
           stat_of(json, 1, "rays_finished"), T);
    free(json);
}

void suite_mpi(void)
{
    test_run("mpi: == trace --direct at 1-4 ranks, proxies, memory, ownerships", test_equal_direct);
    test_run("mpi: rays crossing ranks many times; proxies cut the bytes sent", test_crossings_and_proxies);
    test_run("mpi: a failed rank ends the run, no output, no hang", test_failures);
    test_run("mpi: rank 0 builds the scene file trace --batched builds (--proxy-res, --point-tris)", test_builds_trace_scene);
    test_run("mpi: SIGINT during rank 0's scene build leaves no file", test_interrupted_build);
    test_run("mpi: rays leave in messages of at most 4096 (at, one before, one past)", test_ray_messages);
    test_run("mpi: hits gathered in chunks across the split (small build)", test_result_chunks);
    test_run("mpi: statistics per rank: sums, shares, owners, loads, messages", test_statistics);
    test_run("mpi: failed secondary paths leave no file; --rays-in-flight 1", test_failure_paths);
    test_run("mpi long: 2^20 + 1 results from one rank (make test-long)", test_long_results);
}
