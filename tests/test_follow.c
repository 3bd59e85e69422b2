/*
** tests/test_follow.c -- trace --follow N: one ray's journey through the
** method (brt_trace_options.follow), checked against what the same run
** writes without it.
**
** The journey is only worth reading if it is the ray's true path, so the
** tests follow every ray of a small file, one run each, and add up what
** the journeys say: the visits (queued + intersected at once), the proxy
** tests and culls must equal the statistics of one run over the whole
** file, each journey's own count of visits must equal its "finished"
** line, and each final answer must be the ray's record in the hit (or
** occlusion) file.  Under a tight memory limit, both schedulers and two
** threads, so queues, loads, resident visits and culls all occur.
*/
#include "test.h"
#include "util.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* What one journey says, counted line by line. */
typedef struct journey {
    unsigned queued, resident, proxy_hits, proxy_misses, loads, finished;
    unsigned final_visits;      /* the "finished" line's count */
    unsigned late_enters;       /* boxes entered beyond the closest hit so far */
    int final_hit;              /* 1: a triangle (or occluded), 0: none */
    unsigned final_prim;
    float final_t;
} journey;

static int read_journey(const char *text, journey *j)
{
    const char *line = text;
    float closest = (float)INFINITY;
    memset(j, 0, sizeof *j);
    if (!text || strncmp(text, "ray ", 4) != 0) return 0;
    while ((line = strchr(line, '\n')) != NULL) {
        char word[16];
        line++;
        if (sscanf(line, " %15s", word) != 1) continue;
        if (strcmp(word, "enter") == 0) {
            const char *at = strstr(line, "t = ");
            j->late_enters += at && strtof(at + 4, NULL) > closest;
        } else if (strcmp(word, "triangles") == 0) {
            unsigned prim;
            float t;
            const char *at = strstr(line, "closest so far triangle");
            if (at && sscanf(at, "closest so far triangle %u at t = %g", &prim, &t) == 2) closest = t;
        } else if (strcmp(word, "queued") == 0) j->queued++;
        else if (strcmp(word, "resident") == 0) j->resident++;
        else if (strcmp(word, "load") == 0) j->loads++;
        else if (strcmp(word, "proxy") == 0) {
            if (strstr(line, ": hit,") && strstr(line, ": hit,") < strchr(line, '\n')) j->proxy_hits++;
            else j->proxy_misses++;
        } else if (strcmp(word, "finished") == 0) {
            const char *v;
            j->finished++;
            j->final_hit = sscanf(line, " finished triangle %u at t = %g", &j->final_prim, &j->final_t) == 2 ||
                           strncmp(line, "  finished   occluded", 21) == 0;
            v = strrchr(line, ',');
            if (v) j->final_visits = (unsigned)strtoul(v + 1, NULL, 10);
        }
    }
    return j->finished == 1;
}

enum { FOLLOW_RAYS = 48 };

/* Follows every ray of rays.rays under OPTIONS and checks the sums
** against one run's statistics and each answer against its file. */
static void follow_all(const char *options, int occlusion)
{
    const char *mode = occlusion ? "--occlusion" : "";
    unsigned char *answers;
    char *stats;
    size_t size;
    unsigned long long queued = 0, resident = 0, tests = 0, culled = 0;
    int status, i;
    status = tu_run("trace @/l.ply @/rays.rays @/all.out --batched %s %s --stats @/all.json", mode, options);
    CHECK(status == 0, "trace %s %s: exit status %d", mode, options, status);
    answers = tu_slurp(tu_scratch("all.out"), &size);
    stats = (char *)tu_slurp(tu_scratch("all.json"), NULL);
    CHECK(answers && stats && size == (size_t)FOLLOW_RAYS * (occlusion ? 1 : 16), "no answers or statistics");
    for (i = 0; i < FOLLOW_RAYS; i++) {
        journey j;
        char *told;
        int read;
        status = tu_run("trace @/l.ply @/rays.rays @/one.out --batched %s %s --follow %d", mode, options, i);
        told = tu_last_stdout();
        read = read_journey(told, &j);
        free(told);
        CHECK(status == 0 && read, "trace --follow %d %s: exit %d, no journey", i, options, status);
        EXPECT(j.queued + j.resident == j.final_visits, "ray %d (%s): %u queued + %u resident lines, "
               "finished says %u visits", i, options, j.queued, j.resident, j.final_visits);
        /* Pharr et al.: only boxes entered beyond the current closest hit
        ** are skipped -- and those always are. */
        EXPECT(j.late_enters == 0, "ray %d (%s): %u boxes entered beyond the closest hit so far", i,
               options, j.late_enters);
        EXPECT(j.loads == j.queued, "ray %d (%s): %u queues, %u loads served them", i, options, j.queued,
               j.loads);
        if (occlusion) {
            EXPECT(j.final_hit == answers[i], "ray %d (%s): journey says %s, the file %u", i, options,
                   j.final_hit ? "occluded" : "clear", answers[i]);
        } else {
            brt_hit h;
            memcpy(&h, answers + 16 * (size_t)i, 16);   /* a 16-byte record; little-endian host */
            h.inst = BRT_NO_INST;
            EXPECT(j.final_hit == (h.prim != BRT_NO_PRIM) &&
                   (!j.final_hit || (j.final_prim == h.prim && j.final_t == h.t)),
                   "ray %d (%s): journey ends at prim %u t %.9g, the hit file at prim %u t %.9g", i,
                   options, j.final_prim, j.final_t, h.prim, h.t);
        }
        queued += j.queued;
        resident += j.resident;
        tests += j.proxy_hits + j.proxy_misses;
        culled += j.proxy_misses;
    }
    EXPECT(queued == (unsigned long long)tu_json_number(stats, "queued_visits") &&
           resident == (unsigned long long)tu_json_number(stats, "resident_visits"),
           "%s: journeys show %llu queued and %llu resident visits, the statistics %g and %g", options,
           queued, resident, tu_json_number(stats, "queued_visits"), tu_json_number(stats, "resident_visits"));
    EXPECT(tests == (unsigned long long)tu_json_number(stats, "proxy_tests") &&
           culled == (unsigned long long)tu_json_number(stats, "proxy_culled"),
           "%s: journeys show %llu proxy tests, %llu culled; the statistics %g and %g", options, tests,
           culled, tu_json_number(stats, "proxy_tests"), tu_json_number(stats, "proxy_culled"));
    free(answers);
    free(stats);
}

/* Writes a then b into out (names in the scratch directory). */
static int join_files(const char *a, const char *b, const char *out)
{
    size_t na, nb;
    unsigned char *da = tu_slurp(tu_scratch(a), &na), *db = tu_slurp(tu_scratch(b), &nb), *both;
    int ok = 0;
    both = da && db ? malloc(na + nb) : NULL;
    if (both) {
        memcpy(both, da, na);
        memcpy(both + na, db, nb);
        ok = tu_spill(tu_scratch(out), both, na + nb);
    }
    free(da);
    free(db);
    free(both);
    return ok;
}

static int make_landscape(void)
{
    if (tu_file_exists(tu_scratch("rays.rays"))) return 1;
    return tu_run("mkscene landscape @/l.ply --scale 0.003") == 0 &&
           tu_run("raygen @/l.ply @/cam.rays --kind camera --count 24 --seed 3") == 0 &&
           tu_run("raygen @/l.ply @/bounce.rays --kind bounce --count 24 --seed 4") == 0 &&
           join_files("cam.rays", "bounce.rays", "rays.rays");
}

static const char *const follow_settings[] = {
    "--point-tris 2000 --memory 200K --threads 1 --scene @/f.brs",
    "--point-tris 2000 --memory 200K --threads 2 --scene @/f.brs",
    "--point-tris 2000 --memory 200K --paper-scheduler --scene @/f.brs",
    "--point-tris 2000 --no-proxy --scene @/f.brs",
};

static void test_follow_closest(void)
{
    size_t i;
    CHECK(make_landscape(), "could not make the landscape and its rays");
    for (i = 0; i < sizeof follow_settings / sizeof *follow_settings; i++) follow_all(follow_settings[i], 0);
}

static void test_follow_occlusion(void)
{
    CHECK(make_landscape(), "could not make the landscape and its rays");
    follow_all(follow_settings[0], 1);
    follow_all(follow_settings[2], 1);
}

static void test_follow_errors(void)
{
    char *err;
    int status;
    CHECK(make_landscape(), "could not make the landscape and its rays");
    EXPECT(tu_run("trace @/l.ply @/rays.rays @/x.hits --follow 1") == 1 && !tu_file_exists(tu_scratch("x.hits")),
           "--follow without --batched accepted");
    status = tu_run("trace @/l.ply @/rays.rays @/x.hits --batched --follow %d --scene @/f.brs", FOLLOW_RAYS);
    err = tu_last_stderr();
    EXPECT(status == 1 && err && strstr(err, "--follow") && !tu_file_exists(tu_scratch("x.hits")),
           "--follow past the last ray accepted");
    free(err);
}

void suite_follow(void)
{
    test_run("follow: every journey adds up to the statistics", test_follow_closest);
    test_run("follow: occlusion journeys", test_follow_occlusion);
    test_run("follow: bad --follow", test_follow_errors);
}
