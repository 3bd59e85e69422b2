/*
** examples/lib/common.h -- helpers shared by the programs in examples/ (not part
** of the library): error exits, option parsing with range checks, a
** progress line, and a minimal PNG writer (stored deflate blocks).
*/
#ifndef BRT_EXAMPLES_COMMON_H
#define BRT_EXAMPLES_COMMON_H

#include "batchrt.h"

#include <math.h>
#include <signal.h>
#include <stddef.h>
#include <stdint.h>

/* Prints "PROG: message" on stderr and exits with status 1 (usage errors
** and bad input alike).  Programs, unlike the library, may exit. */
void ex_die(const char *prog, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3), noreturn))
#endif
    ;

/* Dies on an option prog does not know (arg, starting with '-'): "prog:
** unknown option 'arg' (see --help)", or for an option renamed since (one
** vocabulary, README "Programs") the name it has now, e.g. "trace: --res
** is now --proxy-res (see --help)". */
void ex_unknown_option(const char *prog, const char *arg)
#if defined(__GNUC__)
    __attribute__((noreturn))
#endif
    ;

/* Dies with err's message (or the result's name) unless r is BRT_OK; as
** ex_die_interrupted when an interrupt is pending. */
void ex_check(const char *prog, brt_result r, const brt_error *err);

/* Nonzero when any argument is --help or -h: programs then print their
** usage on stdout and exit 0 before looking at anything else. */
int ex_wants_help(int argc, char **argv);

/* Option values with range checks; a bad value dies with a message naming
** the option, e.g. "trace: --proxy-res: expected an integer in 2..1024, got 'x'". */
uint64_t ex_parse_u64(const char *prog, const char *option, const char *text,
                      uint64_t min, uint64_t max);
double ex_parse_double(const char *prog, const char *option, const char *text,
                       double min, double max);
uint64_t ex_parse_size(const char *prog, const char *option, const char *text);
/* A proxy resolution: a power of two in 2..1024 (else dies naming option). */
uint32_t ex_parse_resolution(const char *prog, const char *option, const char *text);

/* The value after option argv[*i] (advancing *i), or dies when missing. */
const char *ex_option_value(const char *prog, int argc, char **argv, int *i);

/* The folder of scene files when --scene is not given: $BRT_SCENE_DIR,
** else $XDG_CACHE_HOME/batchrt, else $HOME/.cache/batchrt, else
** /tmp/batchrt-<uid>.  Creates it (or dies). */
void ex_scene_folder(const char *prog, char *dir, size_t size);

/* The default scene file of a mesh, in that folder: the mesh's base name,
** a hash of its absolute path and the settings, e.g.
** "bunny.obj-1f3a9c2e-b100000-r128.brs". */
void ex_default_scene_path(const char *prog, const char *mesh, uint32_t point_tris,
                           uint32_t res, char *path, size_t size);

/* The default --point-tris of trace, mpi_trace and render (README, "The
** default point size"): few large batching points, as the paper's.  The
** points asked for: EX_FEW_POINTS without a memory limit; with one, enough
** that the cache holds EX_CACHE_POINTS of them, ceil(EX_CACHE_POINTS / f),
** f the limit's share of the geometry bytes -- memory_percent / 100 when
** it is given (> 0), else memory_bytes / (triangles *
** EX_BLOB_BYTES_PER_TRIANGLE) when memory_bytes > 0 -- and never fewer than
** EX_FEW_POINTS.  The size: ceil(triangles / points), at least
** EX_MIN_POINT_TRIS, at most UINT32_MAX (--point-tris's maximum).
** triangles: the scene's unique ones (a mesh's; an instanced scene's
** world triangles plus each prototype's once); 0 gives EX_MIN_POINT_TRIS. */
uint64_t ex_default_point_tris(uint64_t triangles, uint64_t memory_bytes, double memory_percent);

/* The bytes an indexed mesh holds in memory (positions and indices), and
** a note on stderr when they exceed a nonzero memory limit: a run that
** holds the whole mesh (--direct) says so, since the limit then does not
** bound its memory. */
uint64_t ex_mesh_bytes(const brt_mesh *mesh);
void ex_note_mesh_memory(const char *prog, const brt_mesh *mesh, uint64_t limit);

/* Triangles of a stream gathered as corners (9 floats each), in order:
** ex_corners_append is a brt_triangle_fn over an ex_corners. */
typedef struct ex_corners {
    float *corners;
    size_t count, cap;
} ex_corners;
brt_result ex_corners_append(void *corners, const float *triangles, uint32_t count, uint32_t first,
                             brt_error *err);

/* Writes the statistics JSON of brt_stats_write_json with the program's
** own fields after the library's (extra: "  \"name\": value" lines joined
** by ",\n", or NULL), atomically. */
brt_result ex_stats_write(const char *path, const brt_stats *stats, const char *extra,
                          brt_error *err);

/* s as a JSON string body: quotes and backslashes escaped, control
** characters dropped, cut to fit size. */
void ex_json_escape(const char *s, char *out, size_t size);

/* A progress line on stderr, shown only when stderr is a terminal (or
** BRT_PROGRESS=1): "label  42% ...".  done <= total. */
void ex_progress(const char *label, uint64_t done, uint64_t total);
void ex_progress_end(void);

/* Installs (on the first call) a handler for SIGINT and SIGTERM that only
** records the signal (the one async-signal-safe thing to do) and returns
** the flag it sets: for brt_scene_options.interrupt and the program's own
** loops, which then remove their temporary files and call
** ex_die_interrupted.  The handler is reset after the first signal, so a
** second one ends the process at once (without clean-up) when a phase
** does not poll the flag. */
const volatile sig_atomic_t *ex_catch_interrupts(void);

/* The signal caught so far, 0 when none. */
int ex_interrupted(void);

/* Prints "PROG: interrupted by SIGINT" (or SIGTERM) on stderr and exits
** with 128 + the signal number, the shell's convention. */
void ex_die_interrupted(const char *prog)
#if defined(__GNUC__)
    __attribute__((noreturn))
#endif
    ;

/* --disk-speed and --net-speed: slower devices, modelled.  ex_sleep_until
** sleeps until brt_seconds() reaches when (a signal only shortens one
** nap).  ex_slow_disk_read is a brt_read_fn (user: a const uint64_t, the
** bytes per second) that makes each read last at least its bytes / speed:
** it reads, then sleeps out the rest.  That models a hard disk or a
** network share on a fast SSD -- the setting the method was made for,
** where reading dominates and the time a proxy saves follows the bytes it
** saves.  (Latency is not modelled: proxies cut loads and bytes in about
** the same ratio.) */
void ex_sleep_until(double when);
long ex_slow_disk_read(int fd, void *buf, size_t size, uint64_t offset, void *user);

/* PNG of 8-bit RGB pixels (row-major, top row first), encoded with stored
** deflate blocks, CRC-32 and Adler-32.  encode: *png is malloc'd. */
brt_result ex_png_encode_rgb(int width, int height, const unsigned char *rgb,
                             unsigned char **png, size_t *size);
brt_result ex_png_write_rgb(const char *path, int width, int height,
                            const unsigned char *rgb, brt_error *err);
uint32_t ex_crc32(const unsigned char *data, size_t size);
uint32_t ex_adler32(const unsigned char *data, size_t size);

/* Vectors in double (rays, scenes and the referee round once, at the end):
** a . b, a x b, and v scaled to length 1 (a zero v stays zero).  Inline:
** the scene generators call them per vertex. */
static inline double ex_dot3(const double a[3], const double b[3])
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static inline void ex_cross3(const double a[3], const double b[3], double out[3])
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

static inline void ex_normalize3(double v[3])
{
    double len = sqrt(ex_dot3(v, v));
    if (len > 0) { v[0] /= len; v[1] /= len; v[2] /= len; }
}

/* CPU seconds of the process so far (clock()), for benchmarks. */
double ex_cpu_seconds(void);

#endif
