/*
** examples/tools/mkscene.c -- writes a built-in procedural scene (examples/
** scenes.c: the stand-ins for the crown, landscape and island scenes of
** Molenaar and Eisemann 2020) to a mesh file that any program reads.
**
**   build/mkscene NAME OUT.ply|OUT.obj [--scale S] [--seed N]
**
** One name, one scene: the landscape and the island are render's
** instanced scenes, in .ply and .obj baked (every instance's prototype
** in world space, examples/lib/scenes.c), in .pbrt with their instances.
**
** .ply: binary little-endian PLY (float x y z; uchar count, uint32
** indices), 12 bytes per vertex and 13 per triangle.  .obj: "v" and "f"
** lines; coordinates printed with 9 significant digits, which read back
** as the same floats.
**
** A STREAM, NEVER THE MESH
** The crown at scale 2000 is 200 million triangles (5.6 GB of PLY), more than many
** machines hold, so the mesh is written as it is made (ex_scene_write),
** in three steps:
**   1. count: ex_scene_count gives the totals the header needs, from the
**      placements alone (a few per cent of the time);
**   2. stream: the header and then every vertex go to OUT.tmp.<pid>, the
**      faces (which the file wants after all vertices, while the scene
**      makes them surface by surface) to OUT.faces.tmp.<pid>;
**   3. join: the faces are appended to the first file, the part removed,
**      and OUT.tmp.<pid> renamed to OUT.
** So no half-written file ever carries the final name, the memory used
** does not grow with the scale, and the disk holds at most the file and
** its faces once more.  A failure (a full disk) or SIGINT/SIGTERM removes
** both temporary files.  Long runs show a progress line on a terminal.
**
** .pbrt: the instanced landscape or island (examples/lib/scenes.h) as a pbrt-v4
** file that build/trace, build/embree_trace and build/hitdiff read back
** exactly: the world triangles as trianglemesh shapes in stream order, each
** prototype as ObjectBegin "pK" .. ObjectEnd, each instance as
** AttributeBegin Transform [...] ObjectInstance "pK" AttributeEnd, with
** every number printed with 9 significant digits (the same floats back,
** and a Transform after WorldBegin is its own matrix, exactly).  Written
** as the streams run, through a temporary file renamed at the end.
*/
#include "common.h"
#include "scenes.h"
#include "input.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/types.h>
#include <unistd.h>

static const char *const prog = "mkscene";

#define COPY_BYTES ((size_t)1 << 20)   /* the join copies in blocks of 1 MiB */

static void usage(void)
{
    printf("usage: build/mkscene NAME OUT.ply|OUT.obj|OUT.pbrt [--scale S] [--seed N]\n"
           "Writes a built-in procedural scene as a mesh file.\n"
           "\n"
           "  NAME        crown      one closed, heavily subdivided ornate object\n"
           "              landscape  terrain with forests and rocks (instanced, as render's)\n"
           "              island     islands with dense vegetation in a sea (instanced)\n"
           "  OUT         .ply: binary little-endian PLY; .obj: Wavefront OBJ (the landscape\n"
           "              and island baked: every instance in world space); .pbrt: the\n"
           "              landscape or island as a pbrt-v4 file (objects and instances)\n"
           "  --scale S   S in 0.001..%g (default 1); triangles: the crown about 100000 * S,\n"
           "              the landscape and island baked about 6.5 M and 4 M * S (S <= 1)\n"
           "  --seed N    random seed (default 1); the same seed gives the same bytes\n"
           "  --help      this text\n"
           "\n"
           "The mesh is written as it is made, never held in memory.  Prints the\n"
           "triangle count, the time, the peak resident memory and the bounds.\n", EX_SCENE_MAX_SCALE);
}

static int has_suffix(const char *s, const char *suffix)
{
    size_t n = strlen(s), m = strlen(suffix);
    return n >= m && strcmp(s + n - m, suffix) == 0;
}

/* ===================================================================== */
/* The writer: an ex_mesh_sink over two files                            */
/* ===================================================================== */

typedef struct writer {
    const char *path;            /* the final name, for messages */
    int ply;                     /* else OBJ */
    brt_atomic_file file;        /* the main part: OUT.tmp.<pid>, renamed at the end */
    FILE *main, *faces;          /* stdio over file.fd, and OUT.faces.tmp.<pid> */
    char faces_tmp[4096];        /* "" until named */
    uint64_t triangles_total, triangles_done;
    float lo[3], hi[3];          /* bounds of the vertices so far */
} writer;

static brt_result write_error(const writer *w, brt_error *err)
{
    return brt_fail(err, BRT_EIO, "%s: cannot write: %s", w->path,
                    strerror(errno ? errno : EIO));
}

/* The sink's callbacks stop the scene on a signal (BRT_EINTR). */
static brt_result check_interrupt(brt_error *err)
{
    return ex_interrupted() ? brt_fail(err, BRT_EINTR, "interrupted") : BRT_OK;
}

static brt_result write_vertices(void *user, const float *xyz, uint32_t count, brt_error *err)
{
    writer *w = user;
    unsigned char record[12];
    uint32_t i;
    int k;
    for (i = 0; i < count; i++) {
        const float *p = xyz + 3 * (size_t)i;
        for (k = 0; k < 3; k++) {
            uint32_t bits;   /* little-endian records, whatever the host */
            memcpy(&bits, p + k, 4);
            brt_put_le32(record + 4 * k, bits);
            if (p[k] < w->lo[k]) w->lo[k] = p[k];
            if (p[k] > w->hi[k]) w->hi[k] = p[k];
        }
        if (w->ply ? fwrite(record, 12, 1, w->main) != 1
                   : fprintf(w->main, "v %.9g %.9g %.9g\n", p[0], p[1], p[2]) < 0)
            return write_error(w, err);
    }
    return check_interrupt(err);
}

static brt_result write_triangles(void *user, const uint32_t *abc, uint32_t count, brt_error *err)
{
    writer *w = user;
    unsigned char record[13];
    uint32_t i;
    int k;
    record[0] = 3;
    for (i = 0; i < count; i++) {
        const uint32_t *t = abc + 3 * (size_t)i;
        for (k = 0; k < 3; k++) brt_put_le32(record + 1 + 4 * k, t[k]);
        if (w->ply ? fwrite(record, 13, 1, w->faces) != 1
                   : fprintf(w->faces, "f %lu %lu %lu\n", (unsigned long)t[0] + 1,
                             (unsigned long)t[1] + 1, (unsigned long)t[2] + 1) < 0)
            return write_error(w, err);
    }
    w->triangles_done += count;
    ex_progress("writing", w->triangles_done, w->triangles_total);
    return check_interrupt(err);
}

static int write_header(const writer *w, uint64_t vertices, uint64_t triangles)
{
    if (w->ply)
        return fprintf(w->main, "ply\nformat binary_little_endian 1.0\ncomment batchrt mkscene\n"
                       "element vertex %llu\nproperty float x\nproperty float y\n"
                       "property float z\nelement face %llu\n"
                       "property list uchar uint vertex_indices\nend_header\n",
                       (unsigned long long)vertices, (unsigned long long)triangles) >= 0;
    return fprintf(w->main, "# batchrt mkscene: %llu vertices, %llu triangles\n",
                   (unsigned long long)vertices, (unsigned long long)triangles) >= 0;
}

/* Appends the faces part to the main file. */
static brt_result join(writer *w, brt_error *err)
{
    unsigned char *block = malloc(COPY_BYTES);
    uint64_t size, done = 0;
    brt_result r = BRT_OK;
    size_t n;
    off_t end = 0;
    if (!block) return brt_fail(err, BRT_ENOMEM, "out of memory");
    if (fflush(w->faces) != 0 || (end = ftello(w->faces)) < 0 || fseeko(w->faces, 0, SEEK_SET) != 0)
        r = write_error(w, err);
    size = r == BRT_OK ? (uint64_t)end : 0;
    while (r == BRT_OK && (n = fread(block, 1, COPY_BYTES, w->faces)) > 0) {
        if (fwrite(block, 1, n, w->main) != n) r = write_error(w, err);
        done += n;
        ex_progress("joining", done, size);
        if (r == BRT_OK) r = check_interrupt(err);
    }
    if (r == BRT_OK && (ferror(w->faces) || done != size))
        r = brt_fail(err, BRT_EIO, "%s: cannot read back the faces: %s", w->faces_tmp,
                     strerror(errno ? errno : EIO));
    free(block);
    return r;
}

/* Closes both files (a failed close is a failed write: data may be lost),
** removes the faces part and, when r is BRT_OK, renames the main part over
** the output (else removes it). */
static brt_result finish(writer *w, brt_result r, brt_error *err)
{
    if (w->main && fclose(w->main) != 0 && r == BRT_OK) r = write_error(w, err);
    if (w->main) w->file.fd = -1;       /* fclose closed it */
    if (w->faces && fclose(w->faces) != 0 && r == BRT_OK) r = write_error(w, err);
    w->main = w->faces = NULL;
    if (w->faces_tmp[0]) unlink(w->faces_tmp);
    return brt_atomic_close(&w->file, r, err);
}

static brt_result open_parts(writer *w, brt_error *err)
{
    brt_result r;
    if (snprintf(w->faces_tmp, sizeof w->faces_tmp, "%s.faces.tmp.%ld", w->path, (long)getpid())
        >= (int)sizeof w->faces_tmp) {
        w->faces_tmp[0] = 0;
        return brt_fail(err, BRT_EARG, "%s: path too long", w->path);
    }
    r = brt_atomic_open(&w->file, w->path, err);
    if (r != BRT_OK) return r;
    w->main = fdopen(w->file.fd, "wb");
    w->faces = w->main ? fopen(w->faces_tmp, "w+b") : NULL;
    if (!w->faces) return brt_fail(err, BRT_EIO, "%s: cannot create: %s", w->path, strerror(errno));
    return BRT_OK;
}

/* ---- .pbrt: the instanced scenes ---- */

static brt_result pbrt_error(const char *path, brt_error *err)
{
    return brt_fail(err, BRT_EIO, "%s: cannot write: %s", path, strerror(errno));
}

/* One chunk of triangles as one trianglemesh shape. */
static brt_result pbrt_shape(void *user, const float *corners, uint32_t count, uint32_t first,
                             brt_error *err)
{
    FILE *f = user;
    uint32_t i;
    (void)first;
    fprintf(f, "Shape \"trianglemesh\" \"point3 P\" [");
    for (i = 0; i < 9 * count; i++) fprintf(f, "%s%.9g", i % 9 ? " " : "\n  ", corners[i]);
    fprintf(f, " ]\n  \"integer indices\" [");
    for (i = 0; i < 3 * count; i++) fprintf(f, "%s%u", i % 24 ? " " : "\n  ", i);
    fprintf(f, " ]\n");
    return ferror(f) ? brt_fail(err, BRT_EIO, "write error") : check_interrupt(err);
}

/* Instances: the column-major 4x4 of pbrt's Transform, then the object. */
static brt_result pbrt_instances(void *user, const brt_instance *in, uint32_t count, uint32_t first,
                                 brt_error *err)
{
    FILE *f = user;
    uint32_t i;
    (void)first;
    for (i = 0; i < count; i++) {
        const float *m = in[i].xform;
        fprintf(f, "AttributeBegin Transform [%.9g %.9g %.9g 0 %.9g %.9g %.9g 0 %.9g %.9g %.9g 0 "
                "%.9g %.9g %.9g 1] ObjectInstance \"p%u\" AttributeEnd\n", m[0], m[4], m[8], m[1],
                m[5], m[9], m[2], m[6], m[10], m[3], m[7], m[11], (unsigned)in[i].prototype);
    }
    return ferror(f) ? brt_fail(err, BRT_EIO, "write error") : check_interrupt(err);
}

static brt_result pbrt_body(const brt_scene_source *src, FILE *f, brt_error *err)
{
    brt_result r = BRT_OK;
    uint32_t p;
    fprintf(f, "# written by build/mkscene: an instanced scene of batchrt (examples/lib/scenes.h)\n"
               "WorldBegin\n");
    if (src->world.run) r = src->world.run(src->world.user, pbrt_shape, f, err);
    for (p = 0; p < src->prototype_count && r == BRT_OK; p++) {
        fprintf(f, "ObjectBegin \"p%u\"\n", (unsigned)p);
        r = src->prototype(src->user, p, pbrt_shape, f, err);
        fprintf(f, "ObjectEnd\n");
    }
    if (r == BRT_OK) r = src->instances(src->user, pbrt_instances, f, err);
    return r;
}

static void write_pbrt(const ex_scene_recipe *recipe, const char *out)
{
    ex_instanced_scene *scene;
    brt_scene_source src;
    brt_atomic_file file;
    brt_error err;
    brt_result r;
    FILE *f;
    ex_check(prog, ex_instanced_open(recipe->name, recipe->scale, recipe->seed, &scene, &err), &err);
    ex_instanced_source(scene, &src);
    ex_check(prog, brt_atomic_open(&file, out, &err), &err);
    f = fdopen(file.fd, "w");
    r = f ? pbrt_body(&src, f, &err) : pbrt_error(out, &err);
    if (f) {
        if (fclose(f) != 0 && r == BRT_OK) r = pbrt_error(out, &err);
        file.fd = -1;
    }
    r = brt_atomic_close(&file, r, &err);
    ex_check(prog, r, &err);
    printf("%s: %llu unique, %llu instanced triangles, %u instances\n", recipe->name,
           (unsigned long long)ex_instanced_unique(scene),
           (unsigned long long)ex_instanced_instanced(scene), ex_instanced_instance_count(scene));
    ex_instanced_close(scene);
}

/* The three steps of the file comment. */
static brt_result write_scene(const ex_scene_recipe *recipe, writer *w, uint64_t *vertices,
                              brt_error *err)
{
    ex_mesh_sink sink;
    brt_result r = ex_scene_count(recipe, vertices, &w->triangles_total, err);
    if (r != BRT_OK) return r;
    r = open_parts(w, err);
    if (r == BRT_OK && !write_header(w, *vertices, w->triangles_total)) r = write_error(w, err);
    sink.vertices = write_vertices;
    sink.triangles = write_triangles;
    sink.user = w;
    if (r == BRT_OK) r = ex_scene_write(recipe, &sink, err);
    if (r == BRT_OK) r = join(w, err);
    return finish(w, r, err);
}

int main(int argc, char **argv)
{
    ex_scene_recipe recipe;
    const char *out = NULL;
    double seconds;
    uint64_t vertices = 0;
    brt_error err;
    brt_result r;
    writer w;
    int i, k;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    memset(&recipe, 0, sizeof recipe);
    recipe.scale = 1;
    recipe.seed = 1;
    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--scale") == 0)
            recipe.scale = ex_parse_double(prog, "--scale", ex_option_value(prog, argc, argv, &i),
                                           0.001, EX_SCENE_MAX_SCALE);
        else if (strcmp(argv[i], "--seed") == 0)
            recipe.seed = ex_parse_u64(prog, "--seed", ex_option_value(prog, argc, argv, &i), 0,
                                       UINT64_MAX);
        else if (argv[i][0] == '-' && argv[i][1] != 0)
            ex_unknown_option(prog, argv[i]);
        else if (!recipe.name) recipe.name = argv[i];
        else if (!out) out = argv[i];
        else ex_die(prog, "unexpected argument '%s' (see --help)", argv[i]);
    }
    if (!out) ex_die(prog, "expected NAME and OUT.ply|OUT.obj (see --help)");
    if (!ex_scene_is_builtin(recipe.name))
        ex_die(prog, "unknown scene '%s' (built-in: crown, landscape, island)", recipe.name);
    if (ex_input_is_pbrt(out)) {
        ex_catch_interrupts();
        write_pbrt(&recipe, out);
        return 0;
    }
    if (!has_suffix(out, ".ply") && !has_suffix(out, ".obj"))
        ex_die(prog, "%s: the output name must end in .ply, .obj or .pbrt", out);

    memset(&w, 0, sizeof w);
    w.path = out;
    w.ply = has_suffix(out, ".ply");
    for (k = 0; k < 3; k++) {
        w.lo[k] = INFINITY;
        w.hi[k] = -INFINITY;
    }
    ex_catch_interrupts();
    seconds = brt_seconds();
    r = write_scene(&recipe, &w, &vertices, &err);
    ex_progress_end();
    ex_check(prog, r, &err);
    seconds = brt_seconds() - seconds;
    printf("%s: %llu triangles, %llu vertices, written in %.2f s, peak RSS %.1f MiB\n",
           recipe.name, (unsigned long long)w.triangles_total, (unsigned long long)vertices,
           seconds, (double)brt_peak_rss_bytes() / 1048576.0);
    printf("bounds: %g %g %g .. %g %g %g\n", w.lo[0], w.lo[1], w.lo[2], w.hi[0], w.hi[1],
           w.hi[2]);
    return 0;
}
