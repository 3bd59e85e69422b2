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
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

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

/* Runs "mpirun -np RANKS $BRT_BUILD/mpi_trace ARGS" ('@': the scratch
** folder) with env (NAME=VALUE words, or "") under a time limit; stdout
** and stderr to cli.out and cli.err.  Returns the exit status (124: it
** hung). */
static int mpi_run(int ranks, const char *env, const char *fmt, ...)
{
    char args[2048], head[1024];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(args, sizeof args, fmt, ap);
    va_end(ap);
    snprintf(head, sizeof head,
             "env OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 OMPI_MCA_btl=self,vader %s "
             "timeout %d mpirun --oversubscribe -np %d %s/mpi_trace ", env, HANG_SECONDS, ranks, build_dir());
    return tu_shell(head, args, " < /dev/null");
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
                CHECK(mpi_run(ranks, "", "%s @/mpi-%d-%s.rays @/mpi.out --batch-tris 2000 --res 32 "
                              "--scene @/mpi-%d.brs %s %s --assign %s %s", meshes[m], m, kinds[k], m,
                              proxy, memory, assign, occlusion ? "--occlusion" : "") == 0,
                      "%d ranks, %s %s %s: failed: %s", ranks, meshes[m], proxy, memory, tu_last_stderr());
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
        CHECK(mpi_run(4, "", "@/corridor.obj @/corridor.rays @/mpi.out --batch-tris 1 --res 32 "
                      "--scene @/corridor.brs --assign round-robin --stats @/mpi-cross.json %s",
                      proxies ? "" : "--no-proxy") == 0,
              "failed: %s", tu_last_stderr());
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
        status = mpi_run(3, env, "@/mpi-crown.obj @/mpi-0-bounce.rays @/mpi-fail.out --batch-tris 50 "
                         "--res 32 --scene @/mpi-50.brs --assign round-robin --no-proxy");
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

void suite_mpi(void)
{
    test_run("mpi: == trace --direct at 1-4 ranks, proxies, memory, ownerships", test_equal_direct);
    test_run("mpi: rays crossing ranks many times; proxies cut the bytes sent", test_crossings_and_proxies);
    test_run("mpi: a failed rank ends the run, no output, no hang", test_failures);
}
