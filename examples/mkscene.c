/*
** examples/mkscene.c -- writes a built-in procedural scene (examples/
** scenes.c: the stand-ins for the crown, landscape and island scenes of
** Molenaar and Eisemann 2020) to a mesh file that any program reads.
**
**   build/mkscene NAME OUT.ply|OUT.obj [--scale S] [--seed N]
**
** .ply: binary little-endian PLY (float x y z; uchar count, uint32
** indices), 12 bytes per vertex and 13 per triangle.  .obj: "v" and "f"
** lines; coordinates printed with 9 significant digits, which read back
** as the same floats.  The file is streamed to OUT.tmp.<pid> and renamed,
** so no half-written file ever carries the final name, and the file's
** bytes are never held in memory as a whole (the mesh is).
*/
#include "common.h"
#include "scenes.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static const char *const prog = "mkscene";

static void usage(void)
{
    printf("usage: build/mkscene NAME OUT.ply|OUT.obj [--scale S] [--seed N]\n"
           "Writes a built-in procedural scene as a mesh file.\n"
           "\n"
           "  NAME        crown      one closed, heavily subdivided ornate object\n"
           "              landscape  terrain with forests and rocks (open geometry)\n"
           "              island     islands with dense vegetation in a sea\n"
           "  OUT         .ply: binary little-endian PLY; .obj: Wavefront OBJ\n"
           "  --scale S   size: about 100000 * S triangles, S in 0.001..%g (default 1)\n"
           "  --seed N    random seed (default 1); the same seed gives the same bytes\n"
           "  --help      this text\n"
           "\n"
           "Prints the triangle count and the bounds.\n", EX_SCENE_MAX_SCALE);
}

static int has_suffix(const char *s, const char *suffix)
{
    size_t n = strlen(s), m = strlen(suffix);
    return n >= m && strcmp(s + n - m, suffix) == 0;
}

static void put_u32(unsigned char *p, uint32_t v)
{
    p[0] = (unsigned char)v;
    p[1] = (unsigned char)(v >> 8);
    p[2] = (unsigned char)(v >> 16);
    p[3] = (unsigned char)(v >> 24);
}

/* Little-endian records through a buffer (the host may be big-endian). */
static int write_ply(FILE *f, const brt_mesh *m)
{
    unsigned char record[13];
    uint32_t i;
    int k;
    fprintf(f, "ply\nformat binary_little_endian 1.0\ncomment batchrt mkscene\n"
               "element vertex %lu\nproperty float x\nproperty float y\nproperty float z\n"
               "element face %lu\nproperty list uchar uint vertex_indices\nend_header\n",
            (unsigned long)m->vertex_count, (unsigned long)m->triangle_count);
    for (i = 0; i < m->vertex_count; i++) {
        for (k = 0; k < 3; k++) {
            uint32_t bits;
            memcpy(&bits, m->positions + 3 * (size_t)i + k, 4);
            put_u32(record + 4 * k, bits);
        }
        if (fwrite(record, 12, 1, f) != 1) return 0;
    }
    record[0] = 3;
    for (i = 0; i < m->triangle_count; i++) {
        for (k = 0; k < 3; k++) put_u32(record + 1 + 4 * k, m->indices[3 * (size_t)i + k]);
        if (fwrite(record, 13, 1, f) != 1) return 0;
    }
    return 1;
}

static int write_obj(FILE *f, const brt_mesh *m)
{
    uint32_t i;
    fprintf(f, "# batchrt mkscene: %lu vertices, %lu triangles\n",
            (unsigned long)m->vertex_count, (unsigned long)m->triangle_count);
    for (i = 0; i < m->vertex_count; i++) {
        const float *p = m->positions + 3 * (size_t)i;
        if (fprintf(f, "v %.9g %.9g %.9g\n", p[0], p[1], p[2]) < 0) return 0;
    }
    for (i = 0; i < m->triangle_count; i++) {
        const uint32_t *t = m->indices + 3 * (size_t)i;
        if (fprintf(f, "f %lu %lu %lu\n", (unsigned long)t[0] + 1, (unsigned long)t[1] + 1,
                    (unsigned long)t[2] + 1) < 0)
            return 0;
    }
    return 1;
}

/* Streams the mesh to a temporary name, then renames it into place. */
static void write_mesh(const char *path, const brt_mesh *m)
{
    char tmp[4096];
    FILE *f;
    int ok, saved;
    if (snprintf(tmp, sizeof tmp, "%s.tmp.%ld", path, (long)getpid()) >= (int)sizeof tmp)
        ex_die(prog, "%s: path too long", path);
    f = fopen(tmp, "wb");
    if (!f) ex_die(prog, "%s: cannot create: %s", path, strerror(errno));
    ok = has_suffix(path, ".ply") ? write_ply(f, m) : write_obj(f, m);
    saved = errno;
    if (fclose(f) != 0 && ok) { ok = 0; saved = errno; }
    if (ok && rename(tmp, path) != 0) { ok = 0; saved = errno; }
    if (!ok) {
        unlink(tmp);
        ex_die(prog, "%s: cannot write: %s", path, strerror(saved ? saved : EIO));
    }
}

int main(int argc, char **argv)
{
    const char *name = NULL, *out = NULL;
    double scale = 1, seconds;
    uint64_t seed = 1;
    brt_mesh mesh;
    brt_error err;
    float lo[3], hi[3];
    int i;

    if (ex_wants_help(argc, argv)) { usage(); return 0; }
    for (i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--scale") == 0)
            scale = ex_parse_double(prog, "--scale", ex_option_value(prog, argc, argv, &i),
                                    0.001, EX_SCENE_MAX_SCALE);
        else if (strcmp(argv[i], "--seed") == 0)
            seed = ex_parse_u64(prog, "--seed", ex_option_value(prog, argc, argv, &i), 0,
                                UINT64_MAX);
        else if (argv[i][0] == '-' && argv[i][1] != 0)
            ex_die(prog, "unknown option '%s' (see --help)", argv[i]);
        else if (!name) name = argv[i];
        else if (!out) out = argv[i];
        else ex_die(prog, "unexpected argument '%s' (see --help)", argv[i]);
    }
    if (!out) ex_die(prog, "expected NAME and OUT.ply|OUT.obj (see --help)");
    if (!ex_scene_is_builtin(name))
        ex_die(prog, "unknown scene '%s' (built-in: crown, landscape, island)", name);
    if (!has_suffix(out, ".ply") && !has_suffix(out, ".obj"))
        ex_die(prog, "%s: the output name must end in .ply or .obj", out);

    seconds = brt_seconds();
    ex_check(prog, ex_scene_generate(name, scale, seed, &mesh, &err), &err);
    seconds = brt_seconds() - seconds;
    write_mesh(out, &mesh);
    brt_mesh_bounds(&mesh, lo, hi);
    printf("%s: %lu triangles, %lu vertices, generated in %.2f s\n", name,
           (unsigned long)mesh.triangle_count, (unsigned long)mesh.vertex_count, seconds);
    printf("bounds: %g %g %g .. %g %g %g\n", lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]);
    brt_mesh_free(&mesh);
    return 0;
}
