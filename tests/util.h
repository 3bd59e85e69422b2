/*
** tests/util.h -- scenes and rays shared by the test suites: triangle
** soups and meshes built in memory, and the four ray kinds (camera,
** random, bounce from surface points, axis-parallel) drawn from a seed.
*/
#ifndef BRT_TEST_UTIL_H
#define BRT_TEST_UTIL_H

#include "batchrt.h"
#include "testing.h"

typedef struct tu_scene {
    float *pos;
    uint32_t *idx;
    uint32_t vcount, tcount, vcap, tcap;
} tu_scene;

uint32_t tu_add_vertex(tu_scene *s, float x, float y, float z);
void tu_add_triangle(tu_scene *s, uint32_t a, uint32_t b, uint32_t c);
void tu_scene_free(tu_scene *s);
float tu_rnd(uint64_t *st, float lo, float hi);
/* n random triangles of size about `size` in the cube [0,1]^3. */
void tu_random_soup(tu_scene *s, uint64_t *st, uint32_t n, float size);
void tu_scene_transform(tu_scene *s, float scale, float offset);
void tu_scene_bounds(const tu_scene *s, float lo[3], float hi[3]);
const float *tu_vertex(const tu_scene *s, uint32_t tri, int corner);
/* A brt_mesh that refers to the scene's arrays (do not brt_mesh_free it). */
brt_mesh tu_mesh_view(const tu_scene *s);

enum tu_ray_kind { TU_CAMERA, TU_RANDOM, TU_BOUNCE, TU_AXIS, TU_RAY_KINDS };
extern const char *const tu_kind_name[TU_RAY_KINDS];
void tu_random_unit(uint64_t *st, float d[3]);
/* A ray of the given kind around the box [lo, hi]; a quarter of them get a
** finite tfar inside the scene. */
void tu_make_ray(const tu_scene *s, const float lo[3], const float hi[3], int kind,
                 uint64_t *st, brt_ray *r);

/* The brute-force closest hit: every triangle of s through
** brt_intersect_triangle (numbered prim_ids[i], or i when NULL), kept when
** brt_hit_is_closer than *hit (in/out, like brt_bvh_intersect). */
void tu_brute_force(const tu_scene *s, const uint32_t *prim_ids, const brt_ray *ray,
                    brt_hit *hit);

/* The brute-force occlusion answer: 1 when any triangle of s is hit
** (brt_intersect_triangle within the ray's [tnear, tfar]). */
int tu_brute_occluded(const tu_scene *s, const brt_ray *ray);

/* The distance from p to the triangle abc, in double. */
double tu_point_triangle_distance(const double p[3], const double a[3], const double b[3], const double c[3]);

/* An instanced scene in memory: world triangles, up to TU_MAX_PROTOS
** prototypes and instances of them, as a brt_scene_source (chunks of 5
** triangles and 7 instances), and its brute force: every world triangle
** and every instance's every triangle, the ray carried into object space
** by brt_instance_ray (the same transform of the ray as the library's). */
#define TU_MAX_PROTOS 8
typedef struct tu_instanced {
    tu_scene world;
    tu_scene protos[TU_MAX_PROTOS];
    uint32_t proto_count;
    brt_instance *instances;
    uint32_t instance_count, instance_cap;
} tu_instanced;
brt_instance *tu_add_instance(tu_instanced *s, uint32_t prototype, const float xform[12]);
void tu_instanced_free(tu_instanced *s);
void tu_instanced_source(const tu_instanced *s, brt_scene_source *source);
void tu_instanced_brute(const tu_instanced *s, const brt_ray *ray, brt_hit *hit);
int tu_instanced_brute_occluded(const tu_instanced *s, const brt_ray *ray);
/* Four unit squares in the plane z = 1 at x = 0, 2, 4, 6 (y in [0, 1]),
** instances of one prototype of two triangles, and a world triangle far
** off (at x = 100). */
void tu_instanced_squares(tu_instanced *s);

/* Builds a scene file of s at path (brt_scene_build, source stamp 1) and
** opens it; a failure is a test failure, and NULL. */
brt_scene *tu_build_scene(const tu_scene *s, uint32_t point_tris, uint32_t res, unsigned threads,
                          const char *path);

/* A number of a statistics JSON text ("name": value), NaN when absent; and
** the same from a file. */
double tu_json_number(const char *json, const char *name);
double tu_json_file_number(const char *path, const char *name);

/* ---- files and processes (for the command-line tests) ---- */

/* NAME inside the scratch directory (a few rotating buffers). */
const char *tu_scratch(const char *name);
/* Writes text to NAME in the scratch directory, making its folders;
** returns the path (a few rotating buffers).  A failure is a test
** failure. */
const char *tu_put(const char *name, const char *text);
/* Whether this process's peak RSS means what a test of a memory bound
** needs: not under AddressSanitizer or ThreadSanitizer (shadow memory and
** quarantines of freed blocks stay resident) nor valgrind.  When it does
** not, says SKIP with the reason and returns 0. */
int tu_rss_is_meaningful(void);

int tu_file_exists(const char *path);

/* Sleeps ms milliseconds (the programs run beside the test). */
void tu_sleep_ms(long ms);
/* The whole file, NUL-terminated (malloc'd), or NULL; size may be NULL. */
unsigned char *tu_slurp(const char *path, size_t *size);
int tu_spill(const char *path, const void *data, size_t size);
/* args with every '@' replaced by the scratch directory, into out. */
void tu_expand_scratch(const char *args, char *out, size_t size);
/* Runs the shell command HEAD ARGS TAIL, '@' in ARGS expanded, stdout and
** stderr to cli.out and cli.err in the scratch directory; the exit status,
** or -1 when the command died.  tu_run and the MPI tests' runner. */
int tu_shell(const char *head, const char *args, const char *tail);
/* 1 when both files exist and hold the same bytes. */
int tu_same_file_bytes(const char *a, const char *b);
/* Runs "$BRT_BUILD/ARGS" (printf-formatted) with '@' in ARGS standing for
** the scratch directory; stdout and stderr go to cli.out and cli.err
** there.  Returns the exit status, or -1 when the program died. */
int tu_run(const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 1, 2)))
#endif
    ;
char *tu_last_stdout(void);   /* cli.out / cli.err of the last tu_run */
char *tu_last_stderr(void);
/* Nonzero when the scratch directory holds a "*.tmp.*" file, the trace an
** interrupted atomic write would leave. */
int tu_temporary_file_left(void);
/* The number of entries of dir (without . and ..), or -1 when it cannot be
** read; *with_part (when not NULL): how many have part in their name;
** name (when not NULL): one entry's name. */
int tu_dir_entries(const char *dir, const char *part, int *with_part, char *name, size_t size);

/* Decodes an 8-bit RGB PNG made of stored deflate blocks and filter type
** None (what examples/lib/common.c writes), checking every CRC-32 and the
** Adler-32 with definitions written independently of the writer: the
** pixels (malloc'd) and size, or NULL on any violation. */
unsigned char *tu_png_decode(const unsigned char *png, size_t size, int *w, int *h);
/* CRC-32 bit by bit and Adler-32 with a modulo per byte: the definitions. */
uint32_t tu_crc32_bitwise(const unsigned char *data, size_t size);
uint32_t tu_adler32_slow(const unsigned char *data, size_t size);

#endif
