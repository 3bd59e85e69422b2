/*
** tests/fuzz/targets.c -- the fuzz targets declared in targets.h: OBJ and
** PLY from memory, scene files and ray files through temporary files, and
** pbrt-v4 scene files (examples/lib/pbrt.c) as a small file tree in a
** temporary folder.
**
** Every target checks properties, not just survival.  The oracles are the
** ones of the test suite: a brute-force loop over brt_intersect_triangle
** (the exact oracle of the BVH, batchrt.h) and the direct mode (which the
** batched mode must match byte for byte).  The scene target first repairs
** the checksums of the mutated file, as a forger would: without that,
** nearly every mutation would stop at a checksum and the validation of
** the blobs, boxes and proxies behind it would never be reached.
*/
#include "targets.h"
#include "../../examples/lib/pbrt.h"

#include <dirent.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* ===================================================================== */
/* Helpers                                                               */
/* ===================================================================== */

/* A per-process scratch name, so that parallel fuzzers never share one. */
static void temp_path(char *out, size_t size, const char *suffix)
{
    const char *dir = getenv("TMPDIR");
    snprintf(out, size, "%s/batchrt-fuzz-%ld%s", dir && dir[0] ? dir : "/tmp",
             (long)getpid(), suffix);
}

static int write_file(const char *path, const void *data, size_t size)
{
    FILE *f = fopen(path, "wb");
    int ok = f != NULL && (size == 0 || fwrite(data, 1, size, f) == size);
    if (f && fclose(f) != 0) ok = 0;
    return ok;
}

/* Failure messages are one line that starts with the input's name. */
static const char *check_message(const brt_error *err, const char *name)
{
    if (strncmp(err->message, name, strlen(name)) != 0)
        return "an error message does not start with the input's name";
    if (strchr(err->message, '\n')) return "an error message is not one line";
    return NULL;
}

/* The closest hit by brute force: the exact oracle of the BVH. */
static brt_hit brute_force_hit(const brt_mesh *m, const brt_ray *ray)
{
    brt_hit hit;
    uint32_t i;
    brt_hit_clear(&hit);
    for (i = 0; i < m->triangle_count; i++) {
        const uint32_t *t = m->indices + 3 * (size_t)i;
        float d, u, v;
        if (brt_intersect_triangle(ray, m->positions + 3 * (size_t)t[0],
                                   m->positions + 3 * (size_t)t[1],
                                   m->positions + 3 * (size_t)t[2], &d, &u, &v)
            && brt_hit_is_closer(d, BRT_NO_INST, i, &hit)) {
            hit.t = d;
            hit.prim = i;
            hit.u = u;
            hit.v = v;
        }
    }
    return hit;
}

/* Every record a miss (t = +inf, prim = BRT_NO_PRIM, u = v = 0) or a hit
** on one of tri_count triangles at a finite t inside the ray's segment
** (a t that overflowed to infinity would look like a miss's). */
static const char *hits_valid(const brt_ray *rays, const brt_hit *hits, size_t count,
                              uint32_t tri_count)
{
    size_t i;
    for (i = 0; i < count; i++) {
        const brt_hit *h = &hits[i];
        if (h->prim == BRT_NO_PRIM) {
            if (!(h->t == INFINITY) || h->u != 0 || h->v != 0)
                return "a miss record is not t=inf, u=v=0";
        } else if (h->prim >= tri_count) {
            return "a hit names a triangle beyond the mesh";
        } else if (!(rays[i].tnear <= h->t && h->t <= rays[i].tfar)) {
            return "a hit lies outside the ray's segment";
        } else if (!isfinite(h->t)) {
            return "a hit at an infinite distance";
        }
    }
    return NULL;
}

/* The BVH's hits: valid, and byte for byte those of the brute-force loop. */
static const char *bvh_matches_oracle(const brt_mesh *m, const brt_bvh *bvh,
                                      const brt_ray *rays, size_t count)
{
    size_t i;
    for (i = 0; i < count; i++) {
        brt_hit hit, expected = brute_force_hit(m, &rays[i]);
        const char *problem;
        brt_hit_clear(&hit);
        brt_bvh_intersect(bvh, &rays[i], &hit);
        if (memcmp(&hit, &expected, sizeof hit) != 0)
            return "a BVH hit differs from the brute-force oracle";
        if ((problem = hits_valid(&rays[i], &hit, 1, m->triangle_count)) != NULL) return problem;
    }
    return NULL;
}

/* ===================================================================== */
/* OBJ and PLY                                                           */
/* ===================================================================== */

/* Rays from the middle of the mesh's box along the 6 axes and 8 diagonals:
** every one starts inside the geometry, whatever its scale. */
static const char *accepted_mesh_traces(const brt_mesh *m)
{
    brt_ray rays[14];
    brt_bvh *bvh = NULL;
    brt_error err;
    float lo[3], hi[3];
    const char *problem = NULL;
    int i, a;
    brt_mesh_bounds(m, lo, hi);
    for (i = 0; i < 14; i++) {
        for (a = 0; a < 3; a++) {
            /* Halves first: lo + hi may overflow near FLT_MAX. */
            rays[i].org[a] = 0.5f * lo[a] + 0.5f * hi[a];
            rays[i].dir[a] = i < 6 ? (float)(a == i / 2) * (i % 2 ? -1.0f : 1.0f)
                                   : ((i - 6) >> a & 1) ? 1.0f : -1.0f;
        }
        rays[i].tnear = 0.0f;
        rays[i].tfar = INFINITY;
    }
    if (brt_bvh_build(m->positions, m->indices, m->triangle_count, NULL, &bvh) != BRT_OK)
        return NULL;   /* out of memory is not a finding */
    if (brt_bvh_check(bvh, &err) != BRT_OK) problem = "the BVH of an accepted mesh fails its checker";
    if (!problem) problem = bvh_matches_oracle(m, bvh, rays, 14);
    brt_bvh_free(bvh);
    return problem;
}

static const char *check_mesh(brt_result r, const brt_mesh *m, const brt_error *err,
                              const char *name)
{
    uint64_t i;
    if (r != BRT_OK) {
        if (r != BRT_EPARSE && r != BRT_ENOMEM)
            return "a mesh reader returned a code other than EPARSE or ENOMEM";
        if (m->positions || m->indices || m->vertex_count || m->triangle_count)
            return "the mesh is not zeroed after an error";
        return check_message(err, name);
    }
    if (m->triangle_count == 0) return "a mesh without triangles was accepted";
    for (i = 0; i < 3 * (uint64_t)m->triangle_count; i++)
        if (m->indices[i] >= m->vertex_count) return "an accepted mesh has an index out of range";
    for (i = 0; i < 3 * (uint64_t)m->vertex_count; i++)
        if (!isfinite(m->positions[i])) return "an accepted mesh has a non-finite coordinate";
    return accepted_mesh_traces(m);
}

static const char *run_obj(const uint8_t *data, size_t size)
{
    brt_mesh mesh;
    brt_error err;
    brt_result r = brt_mesh_parse_obj("fuzz.obj", data, size, &mesh, &err);
    const char *problem = check_mesh(r, &mesh, &err, "fuzz.obj");
    if (r == BRT_OK) brt_mesh_free(&mesh);
    return problem;
}

static const char *run_ply(const uint8_t *data, size_t size)
{
    brt_mesh mesh;
    brt_error err;
    brt_result r = brt_mesh_parse_ply("fuzz.ply", data, size, &mesh, &err);
    const char *problem = check_mesh(r, &mesh, &err, "fuzz.ply");
    if (r == BRT_OK) brt_mesh_free(&mesh);
    return problem;
}

/* ===================================================================== */
/* The fixed mesh and its scene                                          */
/* ===================================================================== */

enum { FIXED_RANDOM = 22, FIXED_TRIS = FIXED_RANDOM + 3, FIXED_VERTS = 3 * FIXED_RANDOM + 3 };

/* 22 random triangles of size about 0.6, an exact duplicate of triangle 0
** (equal t: the tie-break decides), a degenerate one, and a large one in
** the plane z = 0. */
void fuzz_fixed_mesh(brt_mesh *mesh)
{
    static float pos[3 * FIXED_VERTS];
    static uint32_t idx[3 * FIXED_TRIS];
    static const float big[9] = {-1, -1, 0, 3, -1, 0, -1, 3, 0};
    uint64_t rng = 7;
    float centre[3];
    int i;
    for (i = 0; i < 3 * 3 * FIXED_RANDOM; i++) {
        if (i % 9 == 0) {   /* a new triangle: a new centre */
            int a;
            for (a = 0; a < 3; a++) centre[a] = 1.4f * brt_random_float(&rng) - 0.7f;
        }
        pos[i] = centre[i % 3] + 0.6f * brt_random_float(&rng) - 0.3f;
    }
    memcpy(pos + 3 * 3 * FIXED_RANDOM, big, sizeof big);
    for (i = 0; i < 3 * FIXED_RANDOM; i++) idx[i] = (uint32_t)i;
    idx[3 * FIXED_RANDOM] = 0; idx[3 * FIXED_RANDOM + 1] = 1; idx[3 * FIXED_RANDOM + 2] = 2;
    idx[3 * FIXED_RANDOM + 3] = 3; idx[3 * FIXED_RANDOM + 4] = 3; idx[3 * FIXED_RANDOM + 5] = 4;
    for (i = 0; i < 3; i++) idx[3 * FIXED_RANDOM + 6 + i] = 3 * FIXED_RANDOM + (uint32_t)i;
    mesh->positions = pos;
    mesh->indices = idx;
    mesh->vertex_count = FIXED_VERTS;
    mesh->triangle_count = FIXED_TRIS;
}

brt_result fuzz_fixed_scene_build(const char *path, brt_error *err)
{
    brt_scene_options opt;
    brt_mesh mesh;
    fuzz_fixed_mesh(&mesh);
    memset(&opt, 0, sizeof opt);   /* fields added later mean defaults */
    opt.point_tris = 8;   /* 4 batching points */
    opt.proxy_res = 4;
    return brt_scene_build(&mesh, &opt, 0, path, err);
}

/* Built once per process: the mesh, its BVH and its open scene (whose
** file is unlinked at once; the open descriptor keeps it readable). */
static struct {
    int state;   /* 0 not yet, 1 ready, -1 failed */
    brt_mesh mesh;
    brt_bvh *bvh;
    brt_scene *scene;
} fixed;

static int fixed_ready(void)
{
    char path[512];
    brt_error err;
    if (fixed.state != 0) return fixed.state > 0;
    fixed.state = -1;
    fuzz_fixed_mesh(&fixed.mesh);
    temp_path(path, sizeof path, ".fixed.brs");
    if (brt_bvh_build(fixed.mesh.positions, fixed.mesh.indices, fixed.mesh.triangle_count,
                      NULL, &fixed.bvh) != BRT_OK
        || fuzz_fixed_scene_build(path, &err) != BRT_OK)
        return 0;
    if (brt_scene_open(path, &fixed.scene, &err) == BRT_OK) fixed.state = 1;
    unlink(path);
    return fixed.state > 0;
}

/* ===================================================================== */
/* Ray files                                                             */
/* ===================================================================== */

enum { MAX_TRACED = 256 };   /* rays per input, to keep inputs fast */

/* Each ray holds exactly the little-endian floats of its 32 bytes. */
static int rays_equal_bytes(const brt_ray *rays, const uint8_t *data, size_t count)
{
    size_t i;
    int k;
    for (i = 0; i < count; i++) {
        float f[8];
        for (k = 0; k < 8; k++) {
            const uint8_t *p = data + 32 * i + 4 * k;
            uint32_t bits = (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16
                            | (uint32_t)p[3] << 24;
            memcpy(&f[k], &bits, 4);
        }
        if (memcmp(rays[i].org, f, 12) || memcmp(rays[i].dir, f + 3, 12)
            || memcmp(&rays[i].tnear, f + 6, 4) || memcmp(&rays[i].tfar, f + 7, 4))
            return 0;
    }
    return 1;
}

/* The rays through the fixed mesh: BVH == brute force, batched == direct. */
static const char *rays_trace_exactly(const brt_ray *rays, size_t count)
{
    brt_hit direct[MAX_TRACED], batched[MAX_TRACED];
    brt_trace_options opt;
    brt_error err;
    const char *problem;
    size_t i;
    if (count > MAX_TRACED) count = MAX_TRACED;
    if (!fixed_ready()) return "cannot build the fixed mesh's BVH and scene";
    problem = bvh_matches_oracle(&fixed.mesh, fixed.bvh, rays, count);
    if (problem || count == 0) return problem;
    for (i = 0; i < count; i++) {
        brt_hit_clear(&direct[i]);
        brt_bvh_intersect(fixed.bvh, &rays[i], &direct[i]);
    }
    memset(&opt, 0, sizeof opt);
    opt.memory_limit = 1;   /* every load evicts the last one */
    /* 1 to 5 rays in flight (the default of 2^20 slots would cost more
    ** than the trace): the schedule changes, the hits may not. */
    opt.rays_in_flight = 1 + (uint32_t)(count % 5);
    if (brt_scene_trace(fixed.scene, &opt, rays, count, batched, NULL, &err) != BRT_OK)
        return "the batched trace of the fixed scene failed";
    if (memcmp(direct, batched, count * sizeof *direct) != 0)
        return "a batched hit differs from the direct one";
    return NULL;
}

static const char *run_rays(const uint8_t *data, size_t size)
{
    char path[512];
    brt_ray *rays = NULL;
    size_t count = 0;
    brt_error err;
    brt_result r;
    const char *problem = NULL;
    temp_path(path, sizeof path, ".rays");
    if (!write_file(path, data, size)) return "cannot write a temporary file";
    r = brt_rays_read(path, &rays, &count, &err);
    unlink(path);
    if (size % BRT_RAY_BYTES != 0) {
        if (r != BRT_EPARSE) problem = "a ray file of a size not a multiple of 32 was not EPARSE";
        else problem = check_message(&err, path);
    } else if (r != BRT_OK) {
        problem = "a ray file of a multiple of 32 bytes was refused";
    } else if (count != size / BRT_RAY_BYTES || !rays_equal_bytes(rays, data, count)) {
        problem = "the rays read differ from the file's bytes";
    } else {
        problem = rays_trace_exactly(rays, count);
    }
    if (r == BRT_OK) free(rays);
    return problem;
}

/* ===================================================================== */
/* Scene files                                                           */
/* ===================================================================== */


static uint64_t get64(const uint8_t *p) { uint64_t v; memcpy(&v, p, 8); return v; }
static uint32_t get32(const uint8_t *p) { uint32_t v; memcpy(&v, p, 4); return v; }

/* Recomputes the checksum stored at p[at] over file[offset, offset+size)
** when that range lies inside the file; returns 1 when it did. */
static int repair(uint8_t *file, size_t file_size, uint64_t offset, uint64_t size, uint8_t *at)
{
    uint64_t sum;
    if (offset > file_size || size > file_size - offset) return 0;
    sum = brt_checksum64(file + offset, (size_t)size);
    memcpy(at, &sum, 8);
    return 1;
}

/* The layout of batchrt.c's scene file: a 256-byte header with three
** sections {offset, size, checksum} at 56 (the first is the table of
** 80-byte batch entries: blob offset, size, checksum at 24, 32, 40) and
** the header checksum at 248.  Inner checksums first, the header last. */
void fuzz_repair_scene_checksums(uint8_t *file, size_t size)
{
    uint64_t table, entries, i;
    int s;
    if (size < 256 || memcmp(file, "BRTSCENE", 8) != 0) return;
    table = get64(file + 56);
    entries = get32(file + 32);
    for (i = 0; table <= size && i < entries && 80 * (i + 1) <= size - table; i++) {
        uint8_t *entry = file + table + 80 * i;
        repair(file, size, get64(entry + 24), get64(entry + 32), entry + 40);
    }
    for (s = 0; s < 3; s++)
        repair(file, size, get64(file + 56 + 24 * s), get64(file + 64 + 24 * s),
               file + 72 + 24 * s);
    repair(file, size, 0, 248, file + 248);
}

/* A 4 x 4 grid of rays down the z axis over the fixed mesh, and four
** diagonals, with a few finite segments. */
static void scene_probe_rays(brt_ray rays[20])
{
    int i;
    for (i = 0; i < 20; i++) {
        brt_ray *r = &rays[i];
        r->org[0] = i < 16 ? -0.75f + 0.5f * (float)(i % 4) : (i & 1 ? -2.0f : 2.0f);
        r->org[1] = i < 16 ? -0.75f + 0.5f * (float)(i / 4) : (i & 2 ? -2.0f : 2.0f);
        r->org[2] = 3.0f;
        r->dir[0] = i < 16 ? 0.0f : -0.5f * r->org[0];
        r->dir[1] = i < 16 ? 0.0f : -0.5f * r->org[1];
        r->dir[2] = -1.0f;
        r->tnear = i % 5 == 1 ? 2.5f : 0.0f;
        r->tfar = i % 5 == 2 ? 3.0f : INFINITY;
    }
}

static const char *run_scene(const uint8_t *data, size_t size)
{
    char path[512];
    uint8_t *file = malloc(size ? size : 1);
    brt_scene *scene = NULL;
    brt_ray rays[20];
    brt_hit hits[20];
    brt_trace_options opt;
    brt_error err;
    brt_result r;
    const char *problem = NULL;
    if (!file) return NULL;
    memcpy(file, data, size);
    fuzz_repair_scene_checksums(file, size);
    temp_path(path, sizeof path, ".brs");
    if (!write_file(path, file, size)) problem = "cannot write a temporary file";
    free(file);
    if (problem) return problem;
    r = brt_scene_open(path, &scene, &err);
    if (r == BRT_OK) {
        scene_probe_rays(rays);
        memset(&opt, 0, sizeof opt);
        opt.memory_limit = 8192;
        opt.rays_in_flight = 8;
        r = brt_scene_trace(scene, &opt, rays, 20, hits, NULL, &err);
        if (r == BRT_OK)
            problem = hits_valid(rays, hits, 20, brt_scene_triangle_count(scene));
        brt_scene_close(scene);
    }
    if (r != BRT_OK && r != BRT_EFORMAT && r != BRT_ENOMEM)
        problem = "a damaged scene file gave a code other than EFORMAT or ENOMEM";
    else if (r != BRT_OK)
        problem = check_message(&err, path);
    unlink(path);
    return problem;
}

/* ===================================================================== */
/* pbrt-v4 scene files                                                   */
/* ===================================================================== */
/*
** The input is a small file tree: its bytes up to the first line
** "#FILE name" are main.pbrt, and each such line (a comment to pbrt, so a
** seed is a scene as it stands) starts the file name, e.g. an included
** file, a PLY file or a .ply.gz.  The files go into a private folder
** (mkdtemp under $TMPDIR), which is also $TMPDIR while the reader runs
** (its gzip scratch files land there), and are removed after; the folder
** must then be empty: nothing left behind.
**
** What no input may do (the reader opens files by path, may run gzip):
**   - reach outside the folder: inputs holding a '/' are not run, so no
**     string, escapes resolved or not, names a path with a folder part;
**     relative names resolve against main.pbrt's folder (".." and "."
**     are folders there, which the reader refuses);
**   - hang or fork without end: Include chains multiply the work (a file
**     read twice by each of the files above it), and each plymesh ".gz"
**     forks gzip once per run; inputs with more than FUZZ_PBRT_INCLUDES
**     Include/Import or FUZZ_PBRT_SHAPES Shape words are not run (words
**     have no escapes, so counting the bytes counts the directives).
*/

enum { FUZZ_PBRT_FILES = 8, FUZZ_PBRT_INCLUDES = 4, FUZZ_PBRT_SHAPES = 24 };

static size_t count_word(const uint8_t *data, size_t size, const char *word)
{
    size_t n = strlen(word), i, count = 0;
    for (i = 0; i + n <= size; i++) count += memcmp(data + i, word, n) == 0;
    return count;
}

/* A file name the target may write: 1 to 32 of [A-Za-z0-9._-], not a
** folder of its own ("." or ".."). */
static int plain_name(const uint8_t *s, size_t n)
{
    size_t i;
    if (n == 0 || n > 32 || (n <= 2 && s[0] == '.' && s[n - 1] == '.')) return 0;
    for (i = 0; i < n; i++)
        if (!((s[i] >= 'a' && s[i] <= 'z') || (s[i] >= 'A' && s[i] <= 'Z')
              || (s[i] >= '0' && s[i] <= '9') || s[i] == '.' || s[i] == '_' || s[i] == '-'))
            return 0;
    return 1;
}

typedef struct pbrt_tree {
    char dir[512];
    char names[FUZZ_PBRT_FILES][40];
    int count;
} pbrt_tree;

/* Writes the input's files into tree->dir; 0 when a file cannot be made. */
static int pbrt_tree_write(pbrt_tree *tree, const uint8_t *data, size_t size)
{
    static const char marker[] = "\n#FILE ";
    const uint8_t *at = data, *end = data + size;
    const char *name = "main.pbrt";
    size_t name_len = strlen(name);
    while (tree->count < FUZZ_PBRT_FILES) {
        const uint8_t *stop = at;
        char path[600];
        while (stop < end && !(end - stop >= 7 && memcmp(stop, marker, 7) == 0)) stop++;
        if (plain_name((const uint8_t *)name, name_len)) {
            char *slot = tree->names[tree->count];
            memcpy(slot, name, name_len);
            slot[name_len] = 0;
            snprintf(path, sizeof path, "%s/%s", tree->dir, slot);
            tree->count++;   /* counted first: removed even when half written */
            if (!write_file(path, at, (size_t)(stop - at))) return 0;
        }
        if (stop == end) break;
        name = (const char *)stop + 7;
        for (at = stop + 7; at < end && *at != '\n'; at++) {}
        name_len = (size_t)((const char *)at - name);
        if (at < end) at++;
    }
    return 1;
}

/* Removes the files; 0 when the folder is not then empty. */
static int pbrt_tree_remove(const pbrt_tree *tree)
{
    int i;
    for (i = 0; i < tree->count; i++) {
        char path[600];
        snprintf(path, sizeof path, "%s/%s", tree->dir, tree->names[i]);
        unlink(path);
    }
    return rmdir(tree->dir) == 0;
}

/* What the streams delivered: counts, chunk numbering, a hash of the
** corners (to compare two runs), and whether all were finite. */
typedef struct pbrt_tally {
    uint64_t triangles, hash;
    uint32_t prototype_count;
    int misnumbered, not_finite, bad_prototype;
} pbrt_tally;

static brt_result tally_triangles(void *user, const float *corners, uint32_t count, uint32_t first,
                                  brt_error *err)
{
    pbrt_tally *t = user;
    size_t i;
    (void)err;
    if (first != t->triangles || count == 0) t->misnumbered = 1;
    for (i = 0; i < 9 * (size_t)count; i++) {
        uint32_t bits;
        memcpy(&bits, &corners[i], 4);
        t->hash = (t->hash ^ bits) * 1099511628211ull;
        if (!isfinite(corners[i])) t->not_finite = 1;
    }
    t->triangles += count;
    return BRT_OK;
}

static brt_result tally_instances(void *user, const brt_instance *inst, uint32_t count, uint32_t first,
                                  brt_error *err)
{
    pbrt_tally *t = user;
    uint32_t i;
    int k;
    (void)err;
    if (first != t->triangles || count == 0) t->misnumbered = 1;
    for (i = 0; i < count; i++) {
        if (inst[i].prototype >= t->prototype_count) t->bad_prototype = 1;
        for (k = 0; k < 12; k++)
            if (!isfinite(inst[i].xform[k])) t->not_finite = 1;
    }
    t->triangles += count;
    return BRT_OK;
}

/* A failed run: a documented code and one line naming a file of the tree
** (its gzip scratch files are in it too); never "changed", since no file
** did. */
static const char *check_stream_error(brt_result r, const brt_error *err, const char *dir)
{
    if (r != BRT_EPARSE && r != BRT_EIO && r != BRT_ENOMEM)
        return "a pbrt stream failed with a code other than EPARSE, EIO or ENOMEM";
    if (strstr(err->message, "changed since")) return "a pbrt stream found a file changed that was not";
    return r == BRT_ENOMEM ? NULL : check_message(err, dir);
}

/* One triangle stream, run twice: the same triangles both times. */
static const char *check_triangle_runs(const brt_scene_source *src, int prototype, uint32_t id,
                                       const char *dir)
{
    pbrt_tally a, b;
    brt_error err;
    brt_result ra, rb;
    memset(&a, 0, sizeof a);
    memset(&b, 0, sizeof b);
    ra = prototype ? src->prototype(src->user, id, tally_triangles, &a, &err)
                   : src->world.run(src->world.user, tally_triangles, &a, &err);
    if (ra != BRT_OK) return check_stream_error(ra, &err, dir);
    rb = prototype ? src->prototype(src->user, id, tally_triangles, &b, &err)
                   : src->world.run(src->world.user, tally_triangles, &b, &err);
    if (rb != BRT_OK) return "a pbrt stream failed on its second run only";
    if (a.misnumbered) return "a pbrt stream's chunks are not numbered in order";
    if (a.not_finite) return "a pbrt stream delivered a non-finite corner";
    if (a.triangles != b.triangles || a.hash != b.hash) return "two runs of a pbrt stream differ";
    return NULL;
}

static const char *check_pbrt_scene(const ex_pbrt *scene, const char *dir)
{
    brt_scene_source src;
    pbrt_tally inst;
    brt_error err;
    float eye[3], target[3], up[3], fov;
    uint64_t world_shapes;
    uint32_t prototypes, instances, i;
    const char *problem = NULL;
    ex_pbrt_counts(scene, &world_shapes, &prototypes, &instances);
    ex_pbrt_source(scene, &src);
    if ((src.world.run != NULL) != (world_shapes > 0)) return "world shapes counted but not streamed";
    if (src.prototype_count != prototypes) return "a prototype count differs from the source's";
    if (strchr(ex_pbrt_skipped(scene), '\n')) return "the skipped summary is not one line";
    if (ex_pbrt_camera(scene, eye, target, up, &fov, NULL)) {
        if (!(fov > 0 && fov < 180)) return "a camera's fov outside (0, 180)";
        for (i = 0; i < 3; i++)
            if (!isfinite(eye[i]) || !isfinite(target[i]) || !isfinite(up[i])) return "a camera is not finite";
    }
    if (src.world.run) problem = check_triangle_runs(&src, 0, 0, dir);
    for (i = 0; i < prototypes && !problem; i++) problem = check_triangle_runs(&src, 1, i, dir);
    if (problem) return problem;
    memset(&inst, 0, sizeof inst);
    inst.prototype_count = prototypes;
    if (src.instances(src.user, tally_instances, &inst, &err) != BRT_OK) return "the instance stream failed";
    if (inst.triangles != instances || inst.misnumbered) return "the instances streamed differ from the count";
    if (inst.bad_prototype) return "an instance names a prototype beyond the count";
    if (inst.not_finite) return "an instance's transform is not finite";
    return NULL;
}

static const char *run_pbrt(const uint8_t *data, size_t size)
{
    const char *tmp = getenv("TMPDIR");
    char *saved = tmp ? malloc(strlen(tmp) + 1) : NULL;
    char main_path[600];
    pbrt_tree tree;
    ex_pbrt *scene = (ex_pbrt *)&tree;   /* not NULL: must become NULL on error */
    brt_error err;
    brt_result r;
    const char *problem = NULL;
    if (memchr(data, '/', size) || count_word(data, size, "Include") + count_word(data, size, "Import")
        > FUZZ_PBRT_INCLUDES || count_word(data, size, "Shape") > FUZZ_PBRT_SHAPES) {
        free(saved);
        return NULL;
    }
    if (saved) strcpy(saved, tmp);
    memset(&tree, 0, sizeof tree);
    snprintf(tree.dir, sizeof tree.dir, "%s/batchrt-fuzz-pbrt-XXXXXX", tmp && tmp[0] ? tmp : "/tmp");
    if (!mkdtemp(tree.dir)) { free(saved); return "cannot make a temporary folder"; }
    if (!pbrt_tree_write(&tree, data, size)) problem = "cannot write a temporary file";
    snprintf(main_path, sizeof main_path, "%s/main.pbrt", tree.dir);
    setenv("TMPDIR", tree.dir, 1);
    if (!problem) {
        r = ex_pbrt_open(main_path, &scene, &err);
        if (r == BRT_OK) {
            problem = check_pbrt_scene(scene, tree.dir);
            ex_pbrt_close(scene);
        } else if (scene != NULL) {
            problem = "ex_pbrt_open failed without setting its scene to NULL";
        } else if (r != BRT_EPARSE && r != BRT_EIO && r != BRT_ENOMEM) {
            problem = "ex_pbrt_open failed with a code other than EPARSE, EIO or ENOMEM";
        } else if (r != BRT_ENOMEM) {
            problem = check_message(&err, tree.dir);
        }
    }
    if (saved) setenv("TMPDIR", saved, 1);
    else unsetenv("TMPDIR");
    free(saved);
    if (!pbrt_tree_remove(&tree) && !problem) problem = "a file was left in the pbrt folder";
    return problem;
}

/* ===================================================================== */
/* Drivers                                                               */
/* ===================================================================== */

const fuzz_target fuzz_targets[] = {
    {"obj", run_obj}, {"ply", run_ply}, {"scene", run_scene}, {"rays", run_rays},
    {"pbrt", run_pbrt}, {NULL, NULL}};

const fuzz_target *fuzz_find(const char *name)
{
    const fuzz_target *t;
    for (t = fuzz_targets; t->name; t++)
        if (strcmp(t->name, name) == 0) return t;
    return NULL;
}

/* The whole file, malloc'd (at least 1 byte), or NULL. */
static uint8_t *read_file(const char *path, size_t *size)
{
    FILE *f = fopen(path, "rb");
    uint8_t *data = NULL;
    struct stat st;
    if (!f) return NULL;
    if (fstat(fileno(f), &st) == 0 && (data = malloc((size_t)st.st_size + 1)) != NULL
        && fread(data, 1, (size_t)st.st_size, f) != (size_t)st.st_size) {
        free(data);
        data = NULL;
    }
    *size = (size_t)st.st_size;
    fclose(f);
    return data;
}

static long replay_file(const fuzz_target *target, const char *path,
                        void (*report)(const char *, const char *, void *), void *user)
{
    size_t size = 0;
    uint8_t *data = read_file(path, &size);
    const char *problem = data ? target->run(data, size) : "cannot read the input";
    if (problem) report(path, problem, user);
    free(data);
    return 1;
}

long fuzz_replay(const fuzz_target *target, const char *dir,
                 void (*report)(const char *file, const char *problem, void *user), void *user)
{
    DIR *d;
    struct dirent *e;
    struct stat st;
    long count = 0;
    if (stat(dir, &st) != 0) return -1;
    if (S_ISREG(st.st_mode)) return replay_file(target, dir, report, user);
    if ((d = opendir(dir)) == NULL) return -1;
    while ((e = readdir(d)) != NULL) {
        char path[4096];
        if (e->d_name[0] == '.') continue;   /* ".", ".." and hidden files */
        snprintf(path, sizeof path, "%s/%s", dir, e->d_name);
        if (stat(path, &st) == 0 && S_ISREG(st.st_mode))
            count += replay_file(target, path, report, user);
    }
    closedir(d);
    return count;
}

int fuzz_entry(const char *name, const uint8_t *data, size_t size)
{
    const fuzz_target *target = fuzz_find(name);
    const char *problem = target ? target->run(data, size) : "no such fuzz target";
    if (problem) {
        fprintf(stderr, "fuzz target %s: %s\n", name, problem);
        abort();
    }
    return 0;
}
