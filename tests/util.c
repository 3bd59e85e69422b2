/*
** tests/util.c -- scenes and rays shared by the test suites (util.h).
*/
#include "util.h"
#include "test.h"

#include <dirent.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <sys/stat.h>
#include <sys/wait.h>

uint32_t tu_add_vertex(tu_scene *s, float x, float y, float z)
{
    if (s->vcount == s->vcap) {
        s->vcap = s->vcap ? 2 * s->vcap : 64;
        s->pos = realloc(s->pos, 3 * (size_t)s->vcap * sizeof *s->pos);
    }
    s->pos[3 * (size_t)s->vcount] = x;
    s->pos[3 * (size_t)s->vcount + 1] = y;
    s->pos[3 * (size_t)s->vcount + 2] = z;
    return s->vcount++;
}

void tu_add_triangle(tu_scene *s, uint32_t a, uint32_t b, uint32_t c)
{
    if (s->tcount == s->tcap) {
        s->tcap = s->tcap ? 2 * s->tcap : 64;
        s->idx = realloc(s->idx, 3 * (size_t)s->tcap * sizeof *s->idx);
    }
    s->idx[3 * (size_t)s->tcount] = a;
    s->idx[3 * (size_t)s->tcount + 1] = b;
    s->idx[3 * (size_t)s->tcount + 2] = c;
    s->tcount++;
}

void tu_scene_free(tu_scene *s)
{
    free(s->pos);
    free(s->idx);
    memset(s, 0, sizeof *s);
}

float tu_rnd(uint64_t *st, float lo, float hi)
{
    return lo + (hi - lo) * brt_random_float(st);
}

void tu_random_soup(tu_scene *s, uint64_t *st, uint32_t n, float size)
{
    uint32_t i;
    int j;
    for (i = 0; i < n; i++) {
        const float cx = tu_rnd(st, 0, 1), cy = tu_rnd(st, 0, 1), cz = tu_rnd(st, 0, 1);
        uint32_t v[3];
        for (j = 0; j < 3; j++)
            v[j] = tu_add_vertex(s, cx + tu_rnd(st, -size, size), cy + tu_rnd(st, -size, size),
                                 cz + tu_rnd(st, -size, size));
        tu_add_triangle(s, v[0], v[1], v[2]);
    }
}

void tu_scene_transform(tu_scene *s, float scale, float offset)
{
    uint32_t i;
    for (i = 0; i < 3 * s->vcount; i++) s->pos[i] = s->pos[i] * scale + offset;
}

void tu_scene_bounds(const tu_scene *s, float lo[3], float hi[3])
{
    uint32_t i;
    int a;
    for (a = 0; a < 3; a++) { lo[a] = INFINITY; hi[a] = -INFINITY; }
    for (i = 0; i < s->vcount; i++)
        for (a = 0; a < 3; a++) {
            if (s->pos[3 * (size_t)i + a] < lo[a]) lo[a] = s->pos[3 * (size_t)i + a];
            if (s->pos[3 * (size_t)i + a] > hi[a]) hi[a] = s->pos[3 * (size_t)i + a];
        }
}

const float *tu_vertex(const tu_scene *s, uint32_t tri, int corner)
{
    return s->pos + 3 * (size_t)s->idx[3 * (size_t)tri + corner];
}

brt_mesh tu_mesh_view(const tu_scene *s)
{
    brt_mesh m;
    m.positions = s->pos;
    m.indices = s->idx;
    m.vertex_count = s->vcount;
    m.triangle_count = s->tcount;
    return m;
}

const char *const tu_kind_name[TU_RAY_KINDS] = {"camera", "random", "bounce", "axis"};

void tu_random_unit(uint64_t *st, float d[3])
{
    float len;
    do {
        d[0] = tu_rnd(st, -1, 1); d[1] = tu_rnd(st, -1, 1); d[2] = tu_rnd(st, -1, 1);
        len = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    } while (len > 1.0f || len < 1e-4f);
}

void tu_make_ray(const tu_scene *s, const float lo[3], const float hi[3], int kind,
                 uint64_t *st, brt_ray *r)
{
    float c[3], ext = 0;
    int a;
    for (a = 0; a < 3; a++) {
        c[a] = 0.5f * (lo[a] + hi[a]);
        if (hi[a] - lo[a] > ext) ext = hi[a] - lo[a];
    }
    r->tnear = 0.0f;
    r->tfar = INFINITY;
    tu_random_unit(st, r->dir);
    if (kind == TU_CAMERA) {
        /* from a point outside the box towards a point inside it */
        for (a = 0; a < 3; a++) r->org[a] = c[a] + 1.5f * ext * r->dir[a];
        for (a = 0; a < 3; a++) r->dir[a] = tu_rnd(st, lo[a], hi[a]) - r->org[a];
    } else if (kind == TU_RANDOM) {
        for (a = 0; a < 3; a++) r->org[a] = tu_rnd(st, lo[a], hi[a]);
    } else if (kind == TU_BOUNCE && s->tcount > 0) {
        const uint32_t t = (uint32_t)(brt_random_u64(st) % s->tcount);
        float u = brt_random_float(st), v = brt_random_float(st);
        if (u + v > 1.0f) { u = 1.0f - u; v = 1.0f - v; }
        for (a = 0; a < 3; a++)
            r->org[a] = (1 - u - v) * tu_vertex(s, t, 0)[a] + u * tu_vertex(s, t, 1)[a] +
                        v * tu_vertex(s, t, 2)[a];
    } else {
        const int axis = (int)(brt_random_u64(st) % 3);
        for (a = 0; a < 3; a++) { r->org[a] = tu_rnd(st, lo[a], hi[a]); r->dir[a] = 0.0f; }
        r->dir[axis] = brt_random_float(st) < 0.5f ? -1.0f : 1.0f;
        r->org[axis] = r->dir[axis] > 0 ? lo[axis] - ext : hi[axis] + ext;
    }
    if (brt_random_float(st) < 0.25f) r->tfar = tu_rnd(st, 0.0f, 2.0f * ext);
}

/* The oracle of the BVH: every triangle through brt_intersect_triangle,
** the closest by brt_hit_is_closer. */
static void brute_force_named(const tu_scene *s, const uint32_t *prim_ids, uint32_t inst,
                              const brt_ray *ray, brt_hit *hit)
{
    uint32_t i;
    for (i = 0; i < s->tcount; i++) {
        float t, u, v;
        const uint32_t prim = prim_ids ? prim_ids[i] : i;
        if (!brt_intersect_triangle(ray, tu_vertex(s, i, 0), tu_vertex(s, i, 1), tu_vertex(s, i, 2), &t, &u, &v))
            continue;
        if (brt_hit_is_closer(t, inst, prim, hit)) {
            hit->t = t; hit->prim = prim; hit->u = u; hit->v = v; hit->inst = inst;
        }
    }
}

void tu_brute_force(const tu_scene *s, const uint32_t *prim_ids,
                        const brt_ray *ray, brt_hit *hit)
{
    brute_force_named(s, prim_ids, BRT_NO_INST, ray, hit);
}

/* ---- instanced scenes in memory ---- */

brt_instance *tu_add_instance(tu_instanced *s, uint32_t prototype, const float xform[12])
{
    if (s->instance_count == s->instance_cap) {
        s->instance_cap = s->instance_cap ? 2 * s->instance_cap : 16;
        s->instances = realloc(s->instances, s->instance_cap * sizeof *s->instances);
        if (!s->instances) abort();
    }
    s->instances[s->instance_count].prototype = prototype;
    memcpy(s->instances[s->instance_count].xform, xform, 12 * sizeof *xform);
    return &s->instances[s->instance_count++];
}

void tu_instanced_free(tu_instanced *s)
{
    uint32_t p;
    tu_scene_free(&s->world);
    for (p = 0; p < s->proto_count; p++) tu_scene_free(&s->protos[p]);
    free(s->instances);
    memset(s, 0, sizeof *s);
}

/* A tu_scene's triangles as corners, in chunks of 5 (so that chunking is
** exercised). */
static brt_result emit_scene(const tu_scene *s, brt_triangle_fn emit, void *emit_user,
                             brt_error *err)
{
    float corners[5 * 9];
    uint32_t first, k;
    int c;
    for (first = 0; first < s->tcount; first += 5) {
        const uint32_t n = s->tcount - first < 5 ? s->tcount - first : 5;
        brt_result rc;
        for (k = 0; k < n; k++)
            for (c = 0; c < 3; c++) memcpy(corners + 9 * k + 3 * c, tu_vertex(s, first + k, c), 12);
        if ((rc = emit(emit_user, corners, n, first, err)) != BRT_OK) return rc;
    }
    return BRT_OK;
}

static brt_result run_world(const void *user, brt_triangle_fn emit, void *emit_user, brt_error *err)
{
    return emit_scene(&((const tu_instanced *)user)->world, emit, emit_user, err);
}

static brt_result run_prototype(const void *user, uint32_t id, brt_triangle_fn emit,
                                void *emit_user, brt_error *err)
{
    return emit_scene(&((const tu_instanced *)user)->protos[id], emit, emit_user, err);
}

static brt_result run_instances(const void *user, brt_instance_fn emit, void *emit_user,
                                brt_error *err)
{
    const tu_instanced *s = user;
    uint32_t first;
    for (first = 0; first < s->instance_count; first += 7) {
        const uint32_t n = s->instance_count - first < 7 ? s->instance_count - first : 7;
        brt_result rc = emit(emit_user, s->instances + first, n, first, err);
        if (rc != BRT_OK) return rc;
    }
    return BRT_OK;
}

void tu_instanced_source(const tu_instanced *s, brt_scene_source *source)
{
    source->world.run = run_world;
    source->world.user = s;
    source->prototype_count = s->proto_count;
    source->prototype = run_prototype;
    source->instances = run_instances;
    source->user = s;
}

void tu_instanced_brute(const tu_instanced *s, const brt_ray *ray, brt_hit *hit)
{
    uint32_t i;
    brute_force_named(&s->world, NULL, BRT_NO_INST, ray, hit);
    for (i = 0; i < s->instance_count; i++) {
        brt_instance_frame f;
        brt_ray object_ray;
        if (brt_instance_frame_init(&s->instances[i], i, &f, NULL) != BRT_OK) abort();
        brt_instance_ray(&f, ray, &object_ray);
        brute_force_named(&s->protos[s->instances[i].prototype], NULL, i, &object_ray, hit);
    }
}

int tu_instanced_brute_occluded(const tu_instanced *s, const brt_ray *ray)
{
    uint32_t i;
    if (tu_brute_occluded(&s->world, ray)) return 1;
    for (i = 0; i < s->instance_count; i++) {
        brt_instance_frame f;
        brt_ray object_ray;
        if (brt_instance_frame_init(&s->instances[i], i, &f, NULL) != BRT_OK) abort();
        brt_instance_ray(&f, ray, &object_ray);
        if (tu_brute_occluded(&s->protos[s->instances[i].prototype], &object_ray)) return 1;
    }
    return 0;
}

int tu_brute_occluded(const tu_scene *s, const brt_ray *ray)
{
    uint32_t i;
    for (i = 0; i < s->tcount; i++) {
        float t, u, v;
        if (brt_intersect_triangle(ray, tu_vertex(s, i, 0), tu_vertex(s, i, 1), tu_vertex(s, i, 2),
                                   &t, &u, &v))
            return 1;
    }
    return 0;
}

/* ---- files and processes ---- */

/* NAME inside the scratch directory (a few rotating buffers). */
const char *tu_scratch(const char *name)
{
    static char paths[8][512];
    static int next;
    char *out = paths[next++ % 8];
    snprintf(out, 512, "%s/%s", test_tmpdir(), name);
    return out;
}

int tu_file_exists(const char *path)
{
    struct stat st;
    return stat(path, &st) == 0;
}

/* The whole file, NUL-terminated (malloc'd), or NULL. */
unsigned char *tu_slurp(const char *path, size_t *size)
{
    FILE *f = fopen(path, "rb");
    unsigned char *data = NULL;
    long n;
    if (!f) return NULL;
    if (fseek(f, 0, SEEK_END) == 0 && (n = ftell(f)) >= 0 && fseek(f, 0, SEEK_SET) == 0
        && (data = malloc((size_t)n + 1)) != NULL) {
        if (fread(data, 1, (size_t)n, f) == (size_t)n) {
            data[n] = 0;
            if (size) *size = (size_t)n;
        } else {
            free(data);
            data = NULL;
        }
    }
    fclose(f);
    return data;
}

int tu_spill(const char *path, const void *data, size_t size)
{
    FILE *f = fopen(path, "wb");
    int ok = f && fwrite(data, 1, size, f) == size;
    if (f && fclose(f) != 0) ok = 0;
    return ok;
}

/* Runs "$BRT_BUILD/ARGS" with '@' in ARGS standing for the scratch
** directory; stdout and stderr go to cli.out and cli.err there.  Returns
** the exit status, or -1 when the program died from a signal. */
void tu_expand_scratch(const char *args, char *out, size_t size)
{
    const char *dir = test_tmpdir(), *p;
    size_t n = 0;
    for (p = args; *p && n + strlen(dir) + 1 < size; p++) {
        if (*p == '@') { memcpy(out + n, dir, strlen(dir)); n += strlen(dir); }
        else out[n++] = *p;
    }
    out[n] = 0;
}

int tu_shell(const char *head, const char *args, const char *tail)
{
    char expanded[4096], cmd[8192];
    const char *dir = test_tmpdir();
    int status;
    tu_expand_scratch(args, expanded, sizeof expanded);
    snprintf(cmd, sizeof cmd, "%s%s%s > '%s/cli.out' 2> '%s/cli.err'", head, expanded, tail, dir, dir);
    status = system(cmd);
    if (status == -1 || !WIFEXITED(status)) return -1;
    return WEXITSTATUS(status);
}

int tu_run(const char *fmt, ...)
{
    char args[2048], head[1024];
    const char *build = getenv("BRT_BUILD");
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(args, sizeof args, fmt, ap);
    va_end(ap);
    snprintf(head, sizeof head, "%s/", build ? build : "build");
    return tu_shell(head, args, "");
}

int tu_same_file_bytes(const char *a, const char *b)
{
    size_t na = 0, nb = 0;
    unsigned char *x = tu_slurp(a, &na), *y = tu_slurp(b, &nb);
    int same = x && y && na == nb && memcmp(x, y, na) == 0;
    free(x);
    free(y);
    return same;
}

char *tu_last_stdout(void) { return (char *)tu_slurp(tu_scratch("cli.out"), NULL); }

char *tu_last_stderr(void) { return (char *)tu_slurp(tu_scratch("cli.err"), NULL); }

/* Nonzero when the scratch directory holds a "*.tmp.*" file, the trace an
** interrupted atomic write would leave. */
brt_scene *tu_build_scene(const tu_scene *s, uint32_t point_tris, uint32_t res, unsigned threads,
                          const char *path)
{
    brt_scene_options opt;
    brt_mesh mesh = tu_mesh_view(s);
    brt_scene *scene = NULL;
    brt_error err;
    memset(&opt, 0, sizeof opt);   /* fields added later mean defaults */
    opt.point_tris = point_tris;
    opt.proxy_res = res;
    opt.threads = threads;
    if (brt_scene_build(&mesh, &opt, 1, path, &err) != BRT_OK || brt_scene_open(path, &scene, &err) != BRT_OK)
        test_fail_at(__FILE__, __LINE__, "%s: %s", path, err.message);
    return scene;
}

double tu_json_number(const char *json, const char *name)
{
    char key[128];
    const char *p;
    snprintf(key, sizeof key, "\"%s\"", name);
    p = json ? strstr(json, key) : NULL;
    if (!p) return NAN;
    p += strlen(key);
    while (*p == ' ') p++;
    return *p == ':' ? strtod(p + 1, NULL) : NAN;
}

double tu_json_file_number(const char *path, const char *name)
{
    char *json = (char *)tu_slurp(path, NULL);
    double value = tu_json_number(json, name);
    free(json);
    return value;
}

int tu_dir_entries(const char *dir, const char *part, int *with_part, char *name, size_t size)
{
    DIR *d = opendir(dir);
    struct dirent *e;
    int n = 0;
    if (with_part) *with_part = 0;
    if (!d) return -1;
    while ((e = readdir(d)) != NULL) {
        if (strcmp(e->d_name, ".") == 0 || strcmp(e->d_name, "..") == 0) continue;
        n++;
        if (with_part && part && strstr(e->d_name, part)) (*with_part)++;
        if (name) snprintf(name, size, "%s", e->d_name);
    }
    closedir(d);
    return n;
}

int tu_temporary_file_left(void)
{
    int temporary;
    return tu_dir_entries(test_tmpdir(), ".tmp.", &temporary, NULL, 0) < 0 || temporary > 0;
}

/* ---- an independent PNG decoder for the stored-block subset ---- */

static uint32_t get_be32(const unsigned char *p)
{
    return (uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | (uint32_t)p[3];
}

/* CRC-32 bit by bit (no table), the definition of ISO 3309. */
uint32_t tu_crc32_bitwise(const unsigned char *data, size_t size)
{
    uint32_t crc = 0xFFFFFFFFu;
    size_t i;
    int k;
    for (i = 0; i < size; i++) {
        crc ^= data[i];
        for (k = 0; k < 8; k++) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
    }
    return ~crc;
}

/* Adler-32 with a modulo per byte (the definition, not the fast form). */
uint32_t tu_adler32_slow(const unsigned char *data, size_t size)
{
    uint32_t a = 1, b = 0;
    size_t i;
    for (i = 0; i < size; i++) {
        a = (a + data[i]) % 65521u;
        b = (b + a) % 65521u;
    }
    return b << 16 | a;
}

/* Inflates a zlib stream made only of stored blocks into out (capacity
** cap); returns the inflated size or -1 on any violation of RFC 1950/1951. */
static long inflate_stored(const unsigned char *z, size_t size, unsigned char *out, size_t cap)
{
    size_t pos = 2, n = 0;
    int final = 0;
    if (size < 6 || (z[0] & 0x0F) != 8 || ((unsigned)z[0] << 8 | z[1]) % 31 != 0 || (z[1] & 0x20))
        return -1;
    while (!final) {
        uint32_t len, nlen;
        if (pos + 5 > size || (z[pos] >> 1 & 3) != 0) return -1;   /* BTYPE 00 only */
        final = z[pos] & 1;
        len = (uint32_t)z[pos + 1] | (uint32_t)z[pos + 2] << 8;
        nlen = (uint32_t)z[pos + 3] | (uint32_t)z[pos + 4] << 8;
        pos += 5;
        if ((len ^ 0xFFFFu) != nlen || pos + len > size || n + len > cap) return -1;
        memcpy(out + n, z + pos, len);
        pos += len;
        n += len;
    }
    if (pos + 4 != size || get_be32(z + pos) != tu_adler32_slow(out, n)) return -1;
    return (long)n;
}

unsigned char *tu_png_decode(const unsigned char *png, size_t size, int *w, int *h)
{
    static const unsigned char signature[8] = {137, 80, 78, 71, 13, 10, 26, 10};
    size_t pos = 8, idat_size = 0, row = 0, raw_size = 0, y;
    unsigned char *idat = malloc(size ? size : 1), *raw = NULL, *rgb = NULL;
    int seen_ihdr = 0, seen_iend = 0, ok = idat && size > 8 && !memcmp(png, signature, 8);
    while (ok && !seen_iend && pos + 12 <= size) {
        uint32_t len = get_be32(png + pos);
        const unsigned char *type = png + pos + 4, *data = png + pos + 8;
        if (len > size - pos - 12 || get_be32(data + len) != tu_crc32_bitwise(type, len + 4)) {
            ok = 0;
        } else if (!memcmp(type, "IHDR", 4)) {
            ok = !seen_ihdr && pos == 8 && len == 13 && get_be32(data) > 0 && get_be32(data) < 65536
                 && get_be32(data + 4) > 0 && get_be32(data + 4) < 65536 && data[8] == 8
                 && data[9] == 2 && data[10] == 0 && data[11] == 0 && data[12] == 0;
            *w = (int)get_be32(data);
            *h = (int)get_be32(data + 4);
            seen_ihdr = 1;
        } else if (!memcmp(type, "IDAT", 4)) {
            memcpy(idat + idat_size, data, len);
            idat_size += len;
        } else if (!memcmp(type, "IEND", 4)) {
            seen_iend = 1;
            ok = len == 0 && pos + 12 == size;
        }
        pos += 12 + len;
    }
    if (ok && seen_ihdr && seen_iend) {
        row = 3 * (size_t)*w;
        raw_size = (row + 1) * (size_t)*h;
        raw = malloc(raw_size + 1);
        rgb = malloc(row * (size_t)*h);
        ok = raw && rgb && inflate_stored(idat, idat_size, raw, raw_size + 1) == (long)raw_size;
        for (y = 0; ok && y < (size_t)*h; y++) {
            ok = raw[y * (row + 1)] == 0;   /* filter type None, as our writer uses */
            memcpy(rgb + y * row, raw + y * (row + 1) + 1, row);
        }
    } else {
        ok = 0;
    }
    free(idat);
    free(raw);
    if (!ok) {
        free(rgb);
        return NULL;
    }
    return rgb;
}

int tu_rss_is_meaningful(void)
{
    const char *preload = getenv("LD_PRELOAD");
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
    test_skip("under a sanitizer, whose shadow memory and quarantine are resident");
    return 0;
#endif
    if (preload && strstr(preload, "vgpreload")) {
        test_skip("under valgrind, whose shadow memory and freed-block queue are resident");
        return 0;
    }
    return 1;
}

void tu_instanced_squares(tu_instanced *s)
{
    static const float square[4][3] = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0}};
    int k;
    memset(s, 0, sizeof *s);
    s->proto_count = 1;
    for (k = 0; k < 4; k++) tu_add_vertex(&s->protos[0], square[k][0], square[k][1], square[k][2]);
    tu_add_triangle(&s->protos[0], 0, 1, 2);
    tu_add_triangle(&s->protos[0], 0, 2, 3);
    tu_add_triangle(&s->world, tu_add_vertex(&s->world, 100, 0, 0), tu_add_vertex(&s->world, 101, 0, 0),
                    tu_add_vertex(&s->world, 100, 1, 0));
    for (k = 0; k < 4; k++) {
        const float xf[12] = {1, 0, 0, 2.0f * (float)k, 0, 1, 0, 0, 0, 0, 1, 1};
        tu_add_instance(s, 0, xf);
    }
}

const char *tu_put(const char *name, const char *text)
{
    static char paths[8][512];
    static int next;
    char *out = paths[next++ % 8], *slash;
    snprintf(out, 512, "%s", tu_scratch(name));
    for (slash = strchr(out + strlen(test_tmpdir()) + 1, '/'); slash; slash = strchr(slash + 1, '/')) {
        *slash = 0;
        mkdir(out, 0700);
        *slash = '/';
    }
    if (!tu_spill(out, text, strlen(text))) test_fail_at(__FILE__, __LINE__, "cannot write %s", out);
    return out;
}

void tu_sleep_ms(long ms)
{
    struct timespec ts;
    ts.tv_sec = ms / 1000;
    ts.tv_nsec = (ms % 1000) * 1000000L;
    nanosleep(&ts, NULL);
}

/* The distance from p to the triangle abc (closest point by regions,
** Ericson, Real-Time Collision Detection 5.1.5), in double. */
double tu_point_triangle_distance(const double p[3], const double a[3], const double b[3],
                                      const double c[3])
{
    double ab[3], ac[3], ap[3], bp[3], cp[3], q[3], d1 = 0, d2 = 0, d3 = 0, d4 = 0, d5 = 0, d6 = 0;
    double va, vb, vc, v = 0, w = 0, dist = 0;
    int i;
    for (i = 0; i < 3; i++) {
        ab[i] = b[i] - a[i]; ac[i] = c[i] - a[i];
        ap[i] = p[i] - a[i]; bp[i] = p[i] - b[i]; cp[i] = p[i] - c[i];
        d1 += ab[i] * ap[i]; d2 += ac[i] * ap[i]; d3 += ab[i] * bp[i];
        d4 += ac[i] * bp[i]; d5 += ab[i] * cp[i]; d6 += ac[i] * cp[i];
    }
    vc = d1 * d4 - d3 * d2;
    vb = d5 * d2 - d1 * d6;
    va = d3 * d6 - d5 * d4;
    if (d1 <= 0 && d2 <= 0) v = w = 0;                                     /* vertex a */
    else if (d3 >= 0 && d4 <= d3) { v = 1; w = 0; }                        /* vertex b */
    else if (d6 >= 0 && d5 <= d6) { v = 0; w = 1; }                        /* vertex c */
    else if (vc <= 0 && d1 >= 0 && d3 <= 0) { v = d1 / (d1 - d3); w = 0; } /* edge ab */
    else if (vb <= 0 && d2 >= 0 && d6 <= 0) { v = 0; w = d2 / (d2 - d6); } /* edge ac */
    else if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) {                    /* edge bc */
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        v = 1 - w;
    } else if (va + vb + vc != 0) {                                         /* inside */
        v = vb / (va + vb + vc);
        w = vc / (va + vb + vc);
    }
    for (i = 0; i < 3; i++) {
        q[i] = a[i] + v * ab[i] + w * ac[i] - p[i];
        dist += q[i] * q[i];
    }
    return sqrt(dist);
}
