/*
** examples/lib/common.c -- helpers shared by the programs in examples/: error
** exits, option values with range checks, a throttled progress line, a
** SIGINT/SIGTERM flag, and a minimal PNG writer.
**
** The PNG writer follows the PNG specification (ISO/IEC 15948) and RFC 1950
** (zlib) / RFC 1951 (deflate) in their simplest legal form: the image data
** is one zlib stream of STORED (uncompressed) deflate blocks.  Files are a
** little larger than compressed ones, but the writer is short enough to be
** checked by eye, and any PNG reader accepts it.
*/
/* realpath() is in POSIX.1-2008 with the XSI option. */
#define _XOPEN_SOURCE 700
#include "common.h"

#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <limits.h>
#include <signal.h>
#include <time.h>
#include <sys/stat.h>
#include <unistd.h>

/* The default size of a batching point (ex_default_point_tris).  Points
** smaller than EX_MIN_POINT_TRIS never paid: more loads, more disk bytes
** and small threaded phases (make bench-render, make bench-threads). */
#define EX_MIN_POINT_TRIS 100000
/* Without a memory limit every point is in memory anyway: a few large
** points keep the threaded phases large (make bench-threads). */
#define EX_FEW_POINTS 8
/* With a limit, the cache holds this many points at once, so that a load
** does not evict the point the next phase needs (make bench-render). */
#define EX_CACHE_POINTS 4
/* An upper estimate of a blob's bytes per triangle, for an absolute
** limit's share of the geometry: the measured figure is make
** bench-embree's "blob bytes per triangle"; upper, so that the cache holds
** at least EX_CACHE_POINTS. */
#define EX_BLOB_BYTES_PER_TRIANGLE 24

/* ===================================================================== */
/* Errors and options                                                    */
/* ===================================================================== */

void ex_die(const char *prog, const char *fmt, ...)
{
    va_list ap;
    ex_progress_end();
    fprintf(stderr, "%s: ", prog);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    exit(1);
}

void ex_unknown_option(const char *prog, const char *arg)
{
    static const char *const renamed[][2] = {
        {"--res", "--proxy-res"}, {"--batch-tris", "--point-tris"}, {"--batch-instanced", "--point-instanced"}};
    size_t i;
    for (i = 0; i < sizeof renamed / sizeof renamed[0]; i++)
        if (strcmp(arg, renamed[i][0]) == 0) ex_die(prog, "%s is now %s (see --help)", arg, renamed[i][1]);
    ex_die(prog, "unknown option '%s' (see --help)", arg);
}

void ex_check(const char *prog, brt_result r, const brt_error *err)
{
    if (r == BRT_OK) return;
    /* A failure while an interrupt is pending is the interrupt's doing: a
    ** build or trace that polled the flag (BRT_EINTR), or a child (gzip)
    ** that got the same Ctrl-C from the terminal, which signals the whole
    ** process group.  The one place programs turn either into 128 + the
    ** signal. */
    if (ex_interrupted()) ex_die_interrupted(prog);
    ex_die(prog, "%s", err && err->message[0] ? err->message : brt_result_string(r));
}

int ex_wants_help(int argc, char **argv)
{
    int i;
    for (i = 1; i < argc; i++)
        if (strcmp(argv[i], "--help") == 0 || strcmp(argv[i], "-h") == 0) return 1;
    return 0;
}

uint64_t ex_parse_u64(const char *prog, const char *option, const char *text,
                      uint64_t min, uint64_t max)
{
    char *end;
    unsigned long long value;
    errno = 0;
    /* strtoull accepts "-5" (as a huge value) and leading blanks: refuse
    ** both by demanding a digit first. */
    if (text[0] >= '0' && text[0] <= '9') {
        value = strtoull(text, &end, 10);
        if (errno == 0 && *end == 0 && value >= min && value <= max) return value;
    }
    ex_die(prog, "%s: expected an integer in %llu..%llu, got '%s'", option,
           (unsigned long long)min, (unsigned long long)max, text);
}

double ex_parse_double(const char *prog, const char *option, const char *text,
                       double min, double max)
{
    char *end;
    double value;
    errno = 0;
    value = strtod(text, &end);
    /* "!(a <= b)" rather than "a > b" so that NaN is rejected too. */
    if (end == text || *end != 0 || errno == ERANGE || !(value >= min && value <= max))
        ex_die(prog, "%s: expected a number in %g..%g, got '%s'", option, min, max, text);
    return value;
}

uint64_t ex_parse_size(const char *prog, const char *option, const char *text)
{
    uint64_t bytes;
    if (brt_parse_size(text, &bytes) != BRT_OK)
        ex_die(prog, "%s: expected a size above 0 such as 512M (suffix K, M or G), got '%s'",
               option, text);
    return bytes;
}

uint32_t ex_parse_resolution(const char *prog, const char *option, const char *text)
{
    uint64_t res = ex_parse_u64(prog, option, text, 2, 1024);
    if (!brt_proxy_res_valid((uint32_t)res))
        ex_die(prog, "%s: expected a power of two in 2..1024, got '%s'", option, text);
    return (uint32_t)res;
}

const char *ex_option_value(const char *prog, int argc, char **argv, int *i)
{
    if (*i + 1 >= argc) ex_die(prog, "%s needs a value (see --help)", argv[*i]);
    return argv[++*i];
}

/* ===================================================================== */
/* Meshes held whole                                                     */
/* ===================================================================== */

uint64_t ex_mesh_bytes(const brt_mesh *mesh)
{
    return 12 * ((uint64_t)mesh->vertex_count + mesh->triangle_count);
}

/* "12.3 MiB" or, below a MiB, "45.6 KiB". */
static const char *format_bytes(uint64_t bytes, char *text, size_t size)
{
    int mib = bytes >= 1048576;
    snprintf(text, size, "%.1f %s", (double)bytes / (mib ? 1048576.0 : 1024.0), mib ? "MiB" : "KiB");
    return text;
}

void ex_note_mesh_memory(const char *prog, const brt_mesh *mesh, uint64_t limit)
{
    char held[32], limit_text[32];
    if (limit == 0 || ex_mesh_bytes(mesh) <= limit) return;
    fprintf(stderr, "%s: note: the direct run holds the whole mesh in memory (%s of vertices "
            "and indices, and its BVH), more than --memory (%s)\n", prog,
            format_bytes(ex_mesh_bytes(mesh), held, sizeof held),
            format_bytes(limit, limit_text, sizeof limit_text));
}

/* ===================================================================== */
/* Progress line                                                         */
/* ===================================================================== */

static int progress_state = -1;      /* -1 undecided, 0 off, 1 on */
static int progress_drawn;           /* a line is on screen, unterminated */
static double progress_last;         /* time of the last redraw */

static int progress_enabled(void)
{
    if (progress_state < 0) {
        const char *env = getenv("BRT_PROGRESS");
        progress_state = isatty(2) || (env && strcmp(env, "1") == 0);
    }
    return progress_state;
}

void ex_progress(const char *label, uint64_t done, uint64_t total)
{
    double now;
    if (!progress_enabled()) return;
    now = brt_seconds();
    /* Redraw at most ten times a second (and always at the end): a
    ** terminal that redraws per ray would dominate the run time. */
    if (progress_drawn && done < total && now - progress_last < 0.1) return;
    progress_last = now;
    progress_drawn = 1;
    /* Padded so that a shorter label overwrites a longer one. */
    fprintf(stderr, "\r%-16s %3d%%", label,
            total ? (int)(100.0 * (double)done / (double)total) : 100);
    fflush(stderr);
}

void ex_progress_end(void)
{
    if (!progress_drawn) return;
    fputc('\n', stderr);
    progress_drawn = 0;
}

/* ===================================================================== */
/* Interrupts                                                            */
/* ===================================================================== */

/* sig_atomic_t is the one type a handler may write and the program read
** (C99 7.14.1.1); volatile makes every poll read it again. */
static volatile sig_atomic_t interrupt_signal;

static void record_signal(int signo)
{
    interrupt_signal = signo;
}

const volatile sig_atomic_t *ex_catch_interrupts(void)
{
    static int installed;
    struct sigaction action;
    if (installed) return &interrupt_signal;
    installed = 1;
    memset(&action, 0, sizeof action);
    action.sa_handler = record_signal;
    sigemptyset(&action.sa_mask);
    /* SA_RESETHAND: a second signal gets the default action (the process
    ** ends), for a user whose first one a long phase has not seen yet. */
    action.sa_flags = SA_RESETHAND;
    sigaction(SIGINT, &action, NULL);
    sigaction(SIGTERM, &action, NULL);
    return &interrupt_signal;
}

int ex_interrupted(void)
{
    return interrupt_signal;
}

void ex_die_interrupted(const char *prog)
{
    int signo = interrupt_signal ? interrupt_signal : SIGINT;
    ex_progress_end();
    fprintf(stderr, "%s: interrupted by %s\n", prog, signo == SIGTERM ? "SIGTERM" : "SIGINT");
    exit(128 + signo);
}

/* ===================================================================== */
/* Checksums                                                             */
/* ===================================================================== */

uint32_t ex_crc32(const unsigned char *data, size_t size)
{
    /* CRC-32 of ISO 3309 / PNG, reflected polynomial 0xEDB88320, with a
    ** table built on first use. */
    static uint32_t table[256];
    static int ready;
    uint32_t crc = 0xFFFFFFFFu;
    size_t i;
    if (!ready) {
        uint32_t n, c;
        int k;
        for (n = 0; n < 256; n++) {
            for (c = n, k = 0; k < 8; k++) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
            table[n] = c;
        }
        ready = 1;
    }
    for (i = 0; i < size; i++) crc = table[(crc ^ data[i]) & 0xFF] ^ (crc >> 8);
    return crc ^ 0xFFFFFFFFu;
}

uint32_t ex_adler32(const unsigned char *data, size_t size)
{
    /* RFC 1950: two sums modulo 65521; reducing every 5552 bytes is the
    ** longest run that cannot overflow 32 bits. */
    uint32_t a = 1, b = 0;
    while (size > 0) {
        size_t n = size < 5552 ? size : 5552;
        size -= n;
        while (n--) { a += *data++; b += a; }
        a %= 65521u;
        b %= 65521u;
    }
    return (b << 16) | a;
}

/* ===================================================================== */
/* PNG writer                                                            */
/* ===================================================================== */

#define STORED_BLOCK_MAX 65535u   /* LEN is a 16-bit field (RFC 1951 3.2.4) */

/* PNG's numbers are big-endian (its specification, section 7.1): the one
** file batchrt's programs write in that order, so not brt_put_le32. */
static unsigned char *put_be32(unsigned char *p, uint32_t x)
{
    p[0] = (unsigned char)(x >> 24); p[1] = (unsigned char)(x >> 16);
    p[2] = (unsigned char)(x >> 8);  p[3] = (unsigned char)x;
    return p + 4;
}

/* Writes one chunk: length, type, data (already at p + 8), CRC of type
** and data.  Returns the end of the chunk. */
static unsigned char *finish_chunk(unsigned char *p, const char *type, uint32_t length)
{
    put_be32(p, length);
    memcpy(p + 4, type, 4);
    return put_be32(p + 8 + length, ex_crc32(p + 4, 4 + (size_t)length));
}

/* zlib stream of the raw scanlines (each prefixed by filter type 0, "None")
** in stored deflate blocks, written at p; returns its end. */
static unsigned char *write_zlib_stored(unsigned char *p, const unsigned char *raw, size_t size)
{
    size_t done = 0;
    *p++ = 0x78;   /* CMF: deflate, 32K window */
    *p++ = 0x01;   /* FLG: no dictionary; 0x7801 is a multiple of 31 */
    do {
        size_t n = size - done < STORED_BLOCK_MAX ? size - done : STORED_BLOCK_MAX;
        /* Block header: BFINAL in bit 0, BTYPE 00 (stored) in bits 1-2; a
        ** stored block then skips to the byte boundary, so the header is
        ** one whole byte followed by LEN and NLEN, little endian. */
        *p++ = (unsigned char)(done + n == size);
        *p++ = (unsigned char)(n & 0xFF);
        *p++ = (unsigned char)(n >> 8);
        *p++ = (unsigned char)(~n & 0xFF);
        *p++ = (unsigned char)((~n >> 8) & 0xFF);
        memcpy(p, raw + done, n);
        p += n;
        done += n;
    } while (done < size);
    return put_be32(p, ex_adler32(raw, size));
}

brt_result ex_png_encode_rgb(int width, int height, const unsigned char *rgb,
                             unsigned char **png, size_t *size)
{
    static const unsigned char signature[8] = {137, 'P', 'N', 'G', '\r', '\n', 26, '\n'};
    size_t row, rows, raw_size, blocks, zlib_size;
    unsigned char *raw, *out, *p;

    *png = NULL;
    *size = 0;
    /* PNG limits width and height to 2^31-1; the 2^24 cap also keeps the
    ** size arithmetic below far from overflow. */
    if (width < 1 || height < 1 || width > (1 << 24) || height > (1 << 24)
        || (double)width * 3.0 * (double)height > 1e12)
        return BRT_EARG;
    row = 3 * (size_t)width;
    rows = (size_t)height;
    raw_size = (row + 1) * rows;
    blocks = (raw_size + STORED_BLOCK_MAX - 1) / STORED_BLOCK_MAX;
    zlib_size = 2 + 5 * blocks + raw_size + 4;
    if (zlib_size > 0x7FFFFFFFu) return BRT_EARG;   /* one IDAT chunk */

    raw = malloc(raw_size);
    out = malloc(8 + (12 + 13) + (12 + zlib_size) + 12);
    if (!raw || !out) { free(raw); free(out); return BRT_ENOMEM; }
    for (p = raw; p < raw + raw_size; p += row + 1, rgb += row) {
        p[0] = 0;
        memcpy(p + 1, rgb, row);
    }

    memcpy(out, signature, 8);
    p = out + 8;
    put_be32(p + 8, (uint32_t)width);
    put_be32(p + 12, (uint32_t)height);
    p[16] = 8;    /* bit depth */
    p[17] = 2;    /* colour type: RGB */
    p[18] = 0;    /* compression: deflate */
    p[19] = 0;    /* filter method 0 */
    p[20] = 0;    /* no interlace */
    p = finish_chunk(p, "IHDR", 13);
    write_zlib_stored(p + 8, raw, raw_size);
    p = finish_chunk(p, "IDAT", (uint32_t)zlib_size);
    p = finish_chunk(p, "IEND", 0);
    free(raw);
    *png = out;
    *size = (size_t)(p - out);
    return BRT_OK;
}

brt_result ex_png_write_rgb(const char *path, int width, int height,
                            const unsigned char *rgb, brt_error *err)
{
    unsigned char *png;
    size_t size;
    brt_result r = ex_png_encode_rgb(width, height, rgb, &png, &size);
    if (r != BRT_OK)
        return brt_fail(err, r, "%s: cannot encode a %dx%d PNG: %s", path, width, height,
                        brt_result_string(r));
    r = brt_write_file_atomic(path, png, size, err);
    free(png);
    return r;
}

/* ===================================================================== */
/* The default place of scene files                                      */
/* ===================================================================== */

/* mkdir -p: creates every missing folder of path. */
static int make_folders(char *path)
{
    char *p;
    for (p = path + 1; *p; p++) {
        if (*p != '/') continue;
        *p = 0;
        if (mkdir(path, 0755) != 0 && errno != EEXIST) return -1;
        *p = '/';
    }
    return mkdir(path, 0755) != 0 && errno != EEXIST ? -1 : 0;
}

void ex_scene_folder(const char *prog, char *dir, size_t size)
{
    const char *env = getenv("BRT_SCENE_DIR"), *xdg = getenv("XDG_CACHE_HOME"), *home = getenv("HOME");
    if (env && *env) snprintf(dir, size, "%s", env);
    else if (xdg && *xdg) snprintf(dir, size, "%s/batchrt", xdg);
    else if (home && *home) snprintf(dir, size, "%s/.cache/batchrt", home);
    else snprintf(dir, size, "/tmp/batchrt-%ld", (long)getuid());
    if (make_folders(dir) != 0) ex_die(prog, "%s: cannot create the scene folder: %s", dir, strerror(errno));
}

void ex_default_scene_path(const char *prog, const char *mesh, uint32_t point_tris,
                           uint32_t res, char *path, size_t size)
{
    char dir[2048], absolute[PATH_MAX];
    const char *base = strrchr(mesh, '/'), *p;
    uint32_t hash = 2166136261u;   /* FNV-1a of the absolute path */
    ex_scene_folder(prog, dir, sizeof dir);
    if (!realpath(mesh, absolute)) ex_die(prog, "%s: %s", mesh, strerror(errno));
    for (p = absolute; *p; p++) hash = (hash ^ (unsigned char)*p) * 16777619u;
    base = base ? base + 1 : mesh;
    if (snprintf(path, size, "%s/%s-%08x-b%u-r%u.brs", dir, base, (unsigned)hash, (unsigned)point_tris,
                 (unsigned)res) >= (int)size)
        ex_die(prog, "%s: scene path too long", dir);
}

uint64_t ex_default_point_tris(uint64_t triangles, uint64_t memory_bytes, double memory_percent)
{
    uint64_t points = EX_FEW_POINTS, size, want = 0;
    if (memory_percent > 0) {
        /* ceil(EX_CACHE_POINTS / (P / 100)); P is at most a few 100000 */
        double share_points = ceil(EX_CACHE_POINTS * 100.0 / memory_percent);
        want = share_points >= 1e18 ? (uint64_t)1e18 : (uint64_t)share_points;
    } else if (memory_bytes > 0) {
        /* ceil(EX_CACHE_POINTS * T * bytes a triangle / limit), in integers;
        ** a scene beyond 2^56 triangles is out of --point-tris's range anyway */
        uint64_t t = triangles < ((uint64_t)1 << 56) ? triangles : (uint64_t)1 << 56;
        uint64_t geometry = t * EX_CACHE_POINTS * EX_BLOB_BYTES_PER_TRIANGLE;
        want = geometry / memory_bytes + (geometry % memory_bytes != 0);
    }
    if (want > points) points = want;
    size = triangles / points + (triangles % points != 0);
    if (size < EX_MIN_POINT_TRIS) size = EX_MIN_POINT_TRIS;
    return size > UINT32_MAX ? UINT32_MAX : size;
}

double ex_cpu_seconds(void)
{
    return (double)clock() / CLOCKS_PER_SEC;
}

/* ---- statistics with the program's own fields ---- */

brt_result ex_stats_write(const char *path, const brt_stats *stats, const char *extra,
                          brt_error *err)
{
    char *text;
    size_t used;
    brt_result r;
    if (!extra || !*extra) return brt_stats_write_json(path, stats, err);
    if (!(text = malloc(BRT_STATS_JSON_BYTES + strlen(extra) + 8)))
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory", path);
    used = brt_stats_format_json(stats, text);
    /* The library's object ends "\n}\n": the fields go before it. */
    sprintf(text + used - 3, ",\n%s\n}\n", extra);
    r = brt_write_file_atomic(path, text, strlen(text), err);
    free(text);
    return r;
}

void ex_json_escape(const char *s, char *out, size_t size)
{
    size_t n = 0;
    for (; *s && n + 3 < size; s++) {
        if (*s == '"' || *s == '\\') out[n++] = '\\';
        if ((unsigned char)*s >= 0x20) out[n++] = *s;
    }
    out[n] = 0;
}

/* ---- triangle streams gathered ---- */

brt_result ex_corners_append(void *corners, const float *triangles, uint32_t count, uint32_t first,
                             brt_error *err)
{
    ex_corners *g = corners;
    (void)first;
    if (!(g->corners = brt_grow(g->corners, &g->cap, 9 * (g->count + count), sizeof *g->corners)))
        return brt_fail(err, BRT_ENOMEM, "out of memory for %lu triangles",
                        (unsigned long)(g->count + count));
    memcpy(g->corners + 9 * g->count, triangles, 9 * (size_t)count * sizeof *triangles);
    g->count += count;
    return BRT_OK;
}

/* ---- modelled devices ---- */

void ex_sleep_until(double when)
{
    double left;
    while ((left = when - brt_seconds()) > 0) {
        struct timespec ts;
        ts.tv_sec = (time_t)left;
        ts.tv_nsec = (long)((left - (double)ts.tv_sec) * 1e9);
        nanosleep(&ts, NULL);   /* early on a signal: the loop sleeps the rest */
    }
}

long ex_slow_disk_read(int fd, void *buf, size_t size, uint64_t offset, void *user)
{
    const uint64_t *bytes_per_second = user;
    double start = brt_seconds();
    long n = (long)pread(fd, buf, size, (off_t)offset);
    int saved = errno;          /* pread's errno is the cache's to read */
    if (n > 0) ex_sleep_until(start + (double)n / (double)*bytes_per_second);
    errno = saved;
    return n;
}
