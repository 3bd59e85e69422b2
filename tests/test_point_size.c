/*
** tests/test_point_size.c -- the default size of a batching point (issue
** 43; README, "The default point size"; examples/lib/common.c,
** ex_default_point_tris): the rule at its thresholds, from a table worked
** out by hand and from a model written here; the triangle counts the
** programs take before a build, against brt_mesh_load's; and trace and
** render choosing it from a mesh, a pbrt file, the built-in scenes and
** --memory.
*/
#include "test.h"
#include "util.h"
#include "batchrt.h"
#include "../examples/lib/common.h"
#include "../examples/lib/input.h"
#include "../examples/lib/tracer.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The rule as README states it, apart from the programs' integer code:
** points = max(8, ceil(4 / f)), f the limit's share of the geometry (P/100,
** or SIZE / (T * 24 bytes)); size = max(100000, ceil(T / points)). */
static uint64_t model_size(uint64_t t, uint64_t bytes, double percent)
{
    double f = percent > 0 ? percent / 100.0 : bytes ? (double)bytes / ((double)t * 24.0) : 0;
    double points = 8, size;
    if (f > 0 && ceil(4.0 / f) > points) points = ceil(4.0 / f);
    size = ceil((double)t / points);
    return size < 100000 ? 100000 : (uint64_t)size;
}

/* The thresholds, each worked out by hand. */
static void test_rule_thresholds(void)
{
    static const struct { uint64_t t, bytes; double percent; uint64_t want; const char *why; } c[] = {
        {0, 0, 0, 100000, "no triangles known"},
        {799999, 0, 0, 100000, "no limit: 8 points, just below 8 x 100000"},
        {800000, 0, 0, 100000, "no limit: exactly 8 x 100000"},
        {800001, 0, 0, 100001, "no limit: just above 8 x 100000"},
        {8000000, 0, 0, 1000000, "no limit: 8 points"},
        {1600000, 0, 25, 100000, "25 %: ceil(4 / 0.25) = 16 points exactly"},
        {1600001, 0, 25, 100001, "25 %: 16 points, just above 16 x 100000"},
        {3200000, 0, 25, 200000, "25 %: 16 points"},
        {1600000, 0, 50, 200000, "50 %: ceil(4 / 0.5) = 8 points, FEW_POINTS"},
        {1600000, 0, 100, 200000, "100 %: 4 points asked, never fewer than 8"},
        {4000001, 0, 10, 100001, "10 %: 40 points"},
        {3200000, 0, 12.5, 100000, "12.5 %: 32 points exactly"},
        {8000000, 19200000, 0, 200000, "absolute: 8e6 x 24 B, a tenth: 40 points exactly"},
        {8000000, 19200001, 0, 200000, "absolute: a byte more, still 40 points"},
        {8000000, 19199999, 0, 195122, "absolute: a byte less, 41 points"},
        {871414, (uint64_t)1 << 30, 0, 108927, "absolute 1G on the dragon's count: 8 points"},
        {871414, 4u << 20, 0, 100000, "absolute 4M on the dragon's count: 20 points, floor"},
        {(uint64_t)8 * 0xFFFFFFFFu + 8, 0, 0, 0xFFFFFFFFu, "capped at --point-tris's maximum"},
        {(uint64_t)1 << 40, 0, 0, 0xFFFFFFFFu, "capped far beyond it"},
    };
    size_t i;
    for (i = 0; i < sizeof c / sizeof c[0]; i++) {
        uint64_t got = ex_default_point_tris(c[i].t, c[i].bytes, c[i].percent);
        EXPECT(got == c[i].want, "%s: T %llu, --memory %llu B / %g %%: %llu, want %llu", c[i].why,
               (unsigned long long)c[i].t, (unsigned long long)c[i].bytes, c[i].percent,
               (unsigned long long)got, (unsigned long long)c[i].want);
    }
    /* The model agrees off the thresholds too (the cap aside). */
    for (i = 0; i < 2000; i++) {
        uint64_t t = 1000 + (uint64_t)i * 7919 * 13, bytes = i % 3 == 1 ? (uint64_t)(i + 1) * 65537 : 0;
        double percent = i % 3 == 2 ? 0.5 + (double)(i % 97) : 0;
        uint64_t got = ex_default_point_tris(t, bytes, percent), want = model_size(t, bytes, percent);
        EXPECT(got == want, "T %llu, %llu B, %g %%: %llu, model %llu", (unsigned long long)t,
               (unsigned long long)bytes, percent, (unsigned long long)got, (unsigned long long)want);
    }
}

/* The count before a build equals brt_mesh_load's: quads and pentagons
** fanned, comments, blanks (runs of them too), CRLF, a face at the end
** without a newline. */
static void test_mesh_counts(void)
{
    static const struct { const char *name, *text; } files[] = {
        {"count0.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 3 4\n  f\t1 2 3 4 5 # five\n"
                       "# f 1 2 3\nvn 0 0 1\nf 1//1 2//1 3//1\r\nf -1 -2 -3"},
        {"count1.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3 #\n\n\nf 3 2 1"},
        /* a comment straight after the last corner ends the line, not the corner */
        {"count2.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3#g\nf 1 2 3 4#x\nf 4 3 2 1# y\n"},
        /* runs of blanks between corners and after the last are no corners */
        {"count5.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1  2 3 \nf 1 2\t\t3 4  \t\nf  4 3 2\n"},
        {"count3.ply", "ply\nformat ascii 1.0\ncomment element face 99\nelement vertex 3\n"
                       "property float x\nproperty float y\nproperty float z\nelement face 2\n"
                       "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n3 0 1 2\n3 2 1 0\n"},
        /* a PLY written with CRLF line ends (the reader takes them) */
        {"count4.ply", "ply\r\nformat ascii 1.0\r\nelement vertex 3\r\nproperty float x\r\n"
                       "property float y\r\nproperty float z\r\nelement face 3\r\n"
                       "property list uchar int vertex_indices\r\nend_header\r\n0 0 0\r\n1 0 0\r\n1 1 0\r\n"
                       "3 0 1 2\r\n3 2 1 0\r\n3 0 2 1\r\n"},
    };
    size_t i;
    for (i = 0; i < sizeof files / sizeof files[0]; i++) {
        const char *path = tu_put(files[i].name, files[i].text);
        brt_mesh mesh;
        brt_error err;
        CHECK(brt_mesh_load(path, &mesh, &err) == BRT_OK, "%s: %s", files[i].name, err.message);
        EXPECT(ex_mesh_file_triangles(path) == mesh.triangle_count && mesh.triangle_count > 0,
               "%s: counted %llu triangles, loaded %u", files[i].name,
               (unsigned long long)ex_mesh_file_triangles(path), mesh.triangle_count);
        brt_mesh_free(&mesh);
    }
    EXPECT(ex_mesh_file_triangles(tu_scratch("no-such.obj")) == 0, "a missing file counts 0");
}

/* A pbrt file's triangles counted before the build (ex_input_triangles)
** are the unique triangles the build makes (brt_world_build): an indexed
** bilinear mesh of two patches and one without indices (two triangles a
** patch), a loop subdivision, and a prototype counted once for its two
** instances. */
static void test_pbrt_counts(void)
{
    const char *path = tu_put("pc.pbrt",
        "WorldBegin\n"
        "Shape \"bilinearmesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0 1 1 0 2 0 0 2 1 0] \"integer indices\" [0 1 2 3 1 4 3 5]\n"
        "Shape \"bilinearmesh\" \"point3 P\" [0 0 1 1 0 1 0 1 1 1 1 1]\n"
        "Shape \"loopsubdiv\" \"integer levels\" 1 \"point3 P\" [0 0 0 1 0 0 0 1 0 0 0 1] "
        "\"integer indices\" [0 2 1 0 1 3 0 3 2 1 2 3]\n"
        "ObjectBegin \"t\"\nShape \"trianglemesh\" \"point3 P\" [0 0 0 1 0 0 0 1 0] \"integer indices\" [0 1 2]\n"
        "ObjectEnd\nObjectInstance \"t\"\nTranslate 3 0 0\nObjectInstance \"t\"\n");
    ex_input in;
    brt_world *world;
    uint64_t counted, built;
    ex_input_open("point size", path, &in);
    counted = ex_input_triangles(&in);
    world = ex_input_world("point size", &in);
    built = brt_world_unique_triangles(world);
    EXPECT(counted == built && built == 4 + 2 + 16 + 1, "pc.pbrt: counted %llu triangles, the build makes %llu",
           (unsigned long long)counted, (unsigned long long)built);
    brt_world_free(world);
    ex_input_close(&in);
}

/* trace's default --memory 1G is a limit: a scene of more triangles than
** twelve per byte of it asks for more than 8 points (a PLY header alone
** says how many: the counter reads no more). */
static void test_trace_default_limit(void)
{
    const uint64_t t = 200000000;
    ex_tracer_options o;
    ex_input in;
    char header[256];
    snprintf(header, sizeof header, "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
             "property float y\nproperty float z\nelement face %llu\nproperty list uchar int vertex_indices\n"
             "end_header\n", (unsigned long long)t);
    ex_input_open("point size", tu_put("big.ply", header), &in);
    ex_tracer_defaults(&o);
    ex_tracer_point_size(&in, &o);
    EXPECT(o.point_tris == model_size(t, (uint64_t)1 << 30, 0) && o.point_tris < t / 8,
           "%llu triangles under trace's default 1G: points of <= %llu, want %llu",
           (unsigned long long)t, (unsigned long long)o.point_tris,
           (unsigned long long)model_size(t, (uint64_t)1 << 30, 0));
    ex_input_close(&in);
}

/* "... batching points of <= N triangles" of trace --verbose. */
static uint64_t trace_size(void)
{
    const char *err = tu_last_stderr(), *p = err ? strstr(err, "batching points of <= ") : NULL;
    unsigned long long n = 0;
    if (!p || sscanf(p, "batching points of <= %llu", &n) != 1) return 0;
    return n;
}

/* The crown of about 830 000 triangles as PLY and OBJ (above 8 x 100000:
** the default leaves the floor); its triangle count from mkscene. */
static void write_crown(uint64_t *triangles)
{
    unsigned long long t = 0;
    const char *out;
    *triangles = 0;
    CHECK(tu_run("mkscene crown @/ps.ply --scale 8.5") == 0 && tu_run("mkscene crown @/ps.obj --scale 8.5") == 0,
          "mkscene: %s", tu_last_stderr());
    out = tu_last_stdout();
    CHECK(out && sscanf(out, "crown: %llu triangles", &t) == 1 && t > 800000, "mkscene said '%s'", out ? out : "");
    CHECK(tu_run("raygen @/ps.ply @/ps.rays --kind camera --count 64") == 0, "raygen: %s", tu_last_stderr());
    *triangles = t;
}

static void test_trace_default(void)
{
    static const char *const files[] = {"ps.ply", "ps.obj"};
    uint64_t t, want;
    int i;
    write_crown(&t);
    if (test_failed()) return;
    for (i = 0; i < 2; i++) {
        CHECK(tu_run("trace @/%s @/ps.rays @/ps%d.hits --batched --proxy-res 8 --verbose --scene @/ps%d.brs", files[i], i, i) == 0,
              "trace %s: %s", files[i], tu_last_stderr());
        want = model_size(t, (uint64_t)1 << 30, 0);   /* trace's --memory 1G is a limit too */
        EXPECT(trace_size() == want && want > 100000, "trace %s, %llu triangles: points of <= %llu, want %llu",
               files[i], (unsigned long long)t, (unsigned long long)trace_size(), (unsigned long long)want);
    }
    CHECK(tu_run("trace @/ps.ply @/ps.rays @/ps2.hits --batched --proxy-res 8 --verbose --memory 4M --scene @/ps2.brs") == 0,
          "trace --memory 4M: %s", tu_last_stderr());
    want = model_size(t, 4u << 20, 0);
    EXPECT(trace_size() == want, "--memory 4M: points of <= %llu, want %llu", (unsigned long long)trace_size(),
           (unsigned long long)want);
    EXPECT(tu_same_file_bytes(tu_scratch("ps0.hits"), tu_scratch("ps2.hits")), "hits differ between point sizes");
    /* A pbrt file instancing the PLY twice: its triangles count once. */
    tu_put("ps.pbrt", "WorldBegin\nObjectBegin \"c\"\nShape \"plymesh\" \"string filename\" \"ps.ply\"\nObjectEnd\n"
                      "ObjectInstance \"c\"\nTranslate 5 0 0\nObjectInstance \"c\"\n");
    CHECK(tu_run("trace @/ps.pbrt @/ps.rays @/ps3.hits --batched --proxy-res 8 --verbose --scene @/ps3.brs") == 0,
          "trace ps.pbrt: %s", tu_last_stderr());
    want = model_size(t, (uint64_t)1 << 30, 0);
    EXPECT(trace_size() == want, "pbrt, one prototype of %llu triangles twice: points of <= %llu, want %llu",
           (unsigned long long)t, (unsigned long long)trace_size(), (unsigned long long)want);
}

/* render's description line: its triangles (unique ones when instanced)
** and "batching points of <= N". */
static int render_line(const char *scene, unsigned long long *t, unsigned long long *size)
{
    const char *out = tu_last_stdout(), *p;
    size_t n = strlen(scene);
    if (!out || strncmp(out, scene, n) != 0 || out[n] != ':') return 0;
    p = strstr(out, "batching points of <= ");
    return sscanf(out + n + 1, "%llu", t) == 1 && p && sscanf(p, "batching points of <= %llu", size) == 1;
}

static void test_render_default(void)
{
    const char *img = "--width 4 --height 4 --spp 1 --proxy-res 8";
    unsigned long long t = 0, size = 0, t2 = 0, size2 = 0;
    uint64_t want;
    CHECK(tu_run("render crown --scale 8.5 %s --scene @/rc.brs --out @/rc.png --stats @/rc.json", img) == 0,
          "render: %s", tu_last_stderr());
    CHECK(render_line("crown", &t, &size), "render said '%s'", tu_last_stdout());
    want = model_size(t, 0, 0);
    EXPECT(size == want && want > 100000, "crown, %llu triangles, no limit: points of <= %llu, want %llu", t, size,
           (unsigned long long)want);
    EXPECT(tu_json_file_number(tu_scratch("rc.json"), "batching_points") == ceil((double)t / (double)size),
           "%g batching points of %llu triangles, <= %llu each",
           tu_json_file_number(tu_scratch("rc.json"), "batching_points"), t, size);
    CHECK(tu_run("render crown --scale 8.5 %s --memory 40%% --scene @/rc2.brs --out @/rc2.png", img) == 0,
          "render --memory 40%%: %s", tu_last_stderr());
    CHECK(render_line("crown", &t2, &size2), "render said '%s'", tu_last_stdout());
    want = model_size(t2, 0, 40);
    EXPECT(size2 == want && size2 != size, "crown, --memory 40%%: points of <= %llu, want %llu (in core %llu)",
           size2, (unsigned long long)want, size);
    EXPECT(tu_same_file_bytes(tu_scratch("rc.png"), tu_scratch("rc2.png")), "the image depends on the point size");
    CHECK(tu_run("render landscape --scale 9 %s --scene @/rl.brs --out @/rl.png", img) == 0, "render: %s",
          tu_last_stderr());
    CHECK(render_line("landscape", &t, &size), "render said '%s'", tu_last_stdout());
    want = model_size(t, 0, 0);
    EXPECT(size == want && want > 100000, "landscape, %llu unique triangles: points of <= %llu, want %llu", t, size,
           (unsigned long long)want);
}

/* --scene FILE built at another point size is rebuilt, at the same one
** reused (build_seconds 0), the default included. */
static void test_render_scene_reuse(void)
{
    const char *args = "crown --scale 0.3 --width 4 --height 4 --spp 1 --proxy-res 8 --scene @/ru.brs --out @/ru.png";
    static const char *const runs[] = {"", "--point-tris 100000", "--point-tris 50000", ""};
    static const int rebuilt[] = {1, 0, 1, 1};
    int i;
    for (i = 0; i < 4; i++) {
        double built;
        CHECK(tu_run("render %s %s --stats @/ru.json", args, runs[i]) == 0, "render %s: %s", runs[i], tu_last_stderr());
        built = tu_json_file_number(tu_scratch("ru.json"), "build_seconds");
        EXPECT((built > 0) == rebuilt[i], "run %d ('%s' after the runs before): build_seconds %g, want %s", i,
               runs[i], built, rebuilt[i] ? "a build" : "0 (reused)");
    }
}

void suite_point_size(void)
{
    test_run("point size: the rule at its thresholds", test_rule_thresholds);
    test_run("point size: a mesh's triangles counted before the build", test_mesh_counts);
    test_run("point size: a pbrt file's triangles counted as the build makes them", test_pbrt_counts);
    test_run("point size: trace's default 1G is a limit", test_trace_default_limit);
    test_run("point size: trace's default from the mesh, a pbrt file and --memory", test_trace_default);
    test_run("point size: render's default from the built-in scenes and --memory", test_render_default);
    test_run("point size: render --scene FILE rebuilt at another size, reused at the default", test_render_scene_reuse);
}
