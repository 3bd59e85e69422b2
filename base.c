/*
** base.c -- what every part of batchrt stands on, and the only core file
** that calls none of the others: rays and hits (the tie-break every mode
** shares) and their little-endian record files, statistics as JSON,
** results and errors, small utilities (sizes, the 64-bit mixer and
** SplitMix64, little-endian numbers, the growable array, time and peak
** memory, the atomic writer) and a small pool of threads.  bvh.c and
** svdag.c need these, and batchrt.c needs bvh.c and svdag.c, so these live
** below them all (internal.h draws the layers).
*/
#include "internal.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include <pthread.h>
#include <sys/resource.h>
#include <sys/stat.h>

/* ===================================================================== */
/* Rays and hits                                                         */
/* ===================================================================== */

int brt_ray_valid(const brt_ray *ray)
{
    int a;
    for (a = 0; a < 3; a++)
        if (!isfinite(ray->org[a]) || !isfinite(ray->dir[a])) return 0;
    if (ray->dir[0] == 0.0f && ray->dir[1] == 0.0f && ray->dir[2] == 0.0f)
        return 0;
    return ray->tnear <= ray->tfar;   /* false for NaN too */
}

void brt_hit_clear(brt_hit *hit)
{
    hit->t = INFINITY;
    hit->prim = BRT_NO_PRIM;
    hit->u = hit->v = 0.0f;
    hit->inst = BRT_NO_INST;
}

int brt_hit_is_closer(float t, uint32_t inst, uint32_t prim, const brt_hit *current)
{
    if (t != current->t) return t < current->t;
    return inst < current->inst || (inst == current->inst && prim < current->prim);
}

/*
** Ray and hit files are arrays of little-endian 32-bit words (floats as
** their IEEE bit patterns, prim and inst as integers), so one pair of word
** converters serves every record type on any host byte order.  A ray is
** exactly its record, and a hit exactly the long (instanced) record; the
** short hit record is its first four words.
*/
typedef char brt_ray_is_its_record[sizeof(brt_ray) == BRT_RAY_BYTES ? 1 : -1];
typedef char brt_hit_is_its_record[sizeof(brt_hit) == BRT_INST_HIT_BYTES ? 1 : -1];

/* Little-endian words to host words, in place. */
static void words_from_le(void *buffer, size_t words)
{
    unsigned char *b = buffer;
    size_t i;
    for (i = 0; i < words; i++, b += 4) {
        uint32_t w = brt_get_le32(b);
        memcpy(b, &w, 4);
    }
}

static void words_to_le(const void *source, unsigned char *le, size_t words)
{
    const unsigned char *s = source;
    size_t i;
    for (i = 0; i < words; i++, s += 4, le += 4) {
        uint32_t w;
        memcpy(&w, s, 4);
        brt_put_le32(le, w);
    }
}

/* The header of an instanced hit file (batchrt.h, section 3): its first
** word is a NaN, which no hit's t is, so it never begins a short file. */
#define INST_HITS_MAGIC 0x7FB1A5E5u
#define INST_HITS_HEADER 16

static void inst_hits_header(unsigned char h[INST_HITS_HEADER])
{
    brt_put_le32(h, INST_HITS_MAGIC);
    memcpy(h + 4, "INST", 4);
    brt_put_le32(h + 8, 1);
    brt_put_le32(h + 12, BRT_INST_HIT_BYTES);
}

/* The whole file into a malloc'd buffer (+ 1 byte, so an empty file is
** not a NULL buffer). */
static brt_result read_whole(const char *path, unsigned char **data, size_t *size,
                             brt_error *err)
{
    struct stat st;
    unsigned char *buffer;
    size_t done = 0;
    int fd = open(path, O_RDONLY);
    *data = NULL;
    *size = 0;
    if (fd < 0) return brt_fail(err, BRT_EIO, "%s: cannot open: %s", path, strerror(errno));
    if (fstat(fd, &st) != 0) {
        int saved = errno;
        close(fd);
        return brt_fail(err, BRT_EIO, "%s: cannot stat: %s", path, strerror(saved));
    }
    buffer = ((uint64_t)st.st_size == (size_t)st.st_size) ? malloc((size_t)st.st_size + 1) : NULL;
    if (!buffer) {
        close(fd);
        return brt_fail(err, BRT_ENOMEM, "%s: out of memory for %llu bytes", path,
                        (unsigned long long)st.st_size);
    }
    while (done < (size_t)st.st_size) {
        ssize_t n = read(fd, buffer + done, (size_t)st.st_size - done);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) {
            int saved = n < 0 ? errno : EIO;
            free(buffer);
            close(fd);
            return brt_fail(err, BRT_EIO, "%s: read error: %s", path,
                            n < 0 ? strerror(saved) : "file shrank while reading");
        }
        done += (size_t)n;
    }
    close(fd);
    *data = buffer;
    *size = done;
    return BRT_OK;
}

/* Unpacks size bytes of records of record_bytes into host structs of
** struct_bytes each (a prefix of the struct; the rest set by the caller). */
static brt_result unpack_records(const char *path, const unsigned char *le, size_t size,
                                 size_t record_bytes, size_t struct_bytes, const char *what,
                                 void **records, size_t *count, brt_error *err)
{
    unsigned char *out;
    size_t i, n = size / record_bytes;
    if (size % record_bytes != 0)
        return brt_fail(err, BRT_EPARSE,
                        "%s: size %zu is not a multiple of the %zu-byte %s record",
                        path, size, record_bytes, what);
    out = malloc(n ? n * struct_bytes : 1);
    if (!out) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", path);
    for (i = 0; i < n; i++) {
        memcpy(out + i * struct_bytes, le + i * record_bytes, record_bytes);
        words_from_le(out + i * struct_bytes, record_bytes / 4);
    }
    *records = out;
    *count = n;
    return BRT_OK;
}

static brt_result read_records(const char *path, size_t record_bytes, const char *what,
                               void **records, size_t *count, brt_error *err)
{
    unsigned char *data;
    size_t size;
    brt_result rc = read_whole(path, &data, &size, err);
    *records = NULL;
    *count = 0;
    if (rc != BRT_OK) return rc;
    rc = unpack_records(path, data, size, record_bytes, record_bytes, what, records, count, err);
    free(data);
    return rc;
}

/* Writes header (header_bytes, may be 0) and count records: the first
** record_bytes of each struct_bytes-long struct, as little-endian words. */
static brt_result write_records(const char *path, const unsigned char *header,
                                size_t header_bytes, const void *records, size_t count,
                                size_t struct_bytes, size_t record_bytes, brt_error *err)
{
    unsigned char *le;
    brt_result rc;
    size_t i;
    if (count > (SIZE_MAX - header_bytes) / record_bytes)
        return brt_fail(err, BRT_EARG, "%s: too many records", path);
    le = malloc(header_bytes + count * record_bytes + 1);
    if (!le) return brt_fail(err, BRT_ENOMEM, "%s: out of memory", path);
    if (header_bytes) memcpy(le, header, header_bytes);
    for (i = 0; i < count; i++)
        words_to_le((const unsigned char *)records + i * struct_bytes,
                    le + header_bytes + i * record_bytes, record_bytes / 4);
    rc = brt_write_file_atomic(path, le, header_bytes + count * record_bytes, err);
    free(le);
    return rc;
}

brt_result brt_rays_read(const char *path, brt_ray **rays, size_t *count, brt_error *err)
{
    void *records;
    brt_result rc = read_records(path, BRT_RAY_BYTES, "ray", &records, count, err);
    *rays = records;
    return rc;
}

brt_result brt_rays_write(const char *path, const brt_ray *rays, size_t count, brt_error *err)
{
    return write_records(path, NULL, 0, rays, count, BRT_RAY_BYTES, BRT_RAY_BYTES, err);
}

brt_result brt_hits_read(const char *path, brt_hit **hits, size_t *count, int *instanced,
                         brt_error *err)
{
    unsigned char *data, header[INST_HITS_HEADER];
    size_t size, i;
    void *records = NULL;
    int long_form;
    brt_result rc = read_whole(path, &data, &size, err);
    *hits = NULL;
    *count = 0;
    if (rc != BRT_OK) return rc;
    inst_hits_header(header);
    long_form = size >= 4 && brt_get_le32(data) == INST_HITS_MAGIC;
    if (long_form && (size < INST_HITS_HEADER || memcmp(data, header, INST_HITS_HEADER) != 0))
        rc = brt_fail(err, BRT_EPARSE, "%s: bad instanced hit file header", path);
    else if (long_form)
        rc = unpack_records(path, data + INST_HITS_HEADER, size - INST_HITS_HEADER,
                            BRT_INST_HIT_BYTES, sizeof(brt_hit), "instanced hit", &records,
                            count, err);
    else
        rc = unpack_records(path, data, size, BRT_HIT_BYTES, sizeof(brt_hit), "hit", &records,
                            count, err);
    free(data);
    if (rc != BRT_OK) return rc;
    *hits = records;
    if (!long_form)
        for (i = 0; i < *count; i++) (*hits)[i].inst = BRT_NO_INST;
    if (instanced) *instanced = long_form;
    return BRT_OK;
}

brt_result brt_hits_write(const char *path, const brt_hit *hits, size_t count, brt_error *err)
{
    size_t i;
    for (i = 0; i < count; i++)
        if (hits[i].inst != BRT_NO_INST)
            return brt_fail(err, BRT_EARG,
                            "%s: hit %zu names instance %u: an instanced hit file is needed",
                            path, i, (unsigned)hits[i].inst);
    return write_records(path, NULL, 0, hits, count, sizeof(brt_hit), BRT_HIT_BYTES, err);
}

brt_result brt_hits_write_instanced(const char *path, const brt_hit *hits, size_t count,
                                    brt_error *err)
{
    unsigned char header[INST_HITS_HEADER];
    inst_hits_header(header);
    return write_records(path, header, INST_HITS_HEADER, hits, count, sizeof(brt_hit),
                         BRT_INST_HIT_BYTES, err);
}

/* ===================================================================== */
/* Statistics                                                            */
/* ===================================================================== */

/* One JSON object, one field per line.  Counters print as exact integers;
** JSON has no inf or NaN, so a non-finite measurement prints as null. */
/* The object fits: 22 counters of at most 20 digits and 5 measures of
** at most 24 characters, with their names, take under 1,500 bytes. */
size_t brt_stats_format_json(const brt_stats *s, char text[BRT_STATS_JSON_BYTES])
{
    const struct { const char *name; uint64_t value; } counters[] = {
        {"rays", s->rays}, {"batching_points", s->batching_points},
        {"geometry_bytes", s->geometry_bytes}, {"disk_bytes_read", s->disk_bytes_read},
        {"batch_loads", s->batch_loads}, {"cache_peak_bytes", s->cache_peak_bytes},
        {"memory_limit", s->memory_limit}, {"proxy_bytes", s->proxy_bytes},
        {"proxy_tests", s->proxy_tests}, {"proxy_culled", s->proxy_culled},
        {"visits", s->visits}, {"queued_visits", s->queued_visits},
        {"resident_visits", s->resident_visits},
        {"oversized_loads", s->oversized_loads}, {"occlusion_rays", s->occlusion_rays},
        {"occlusion_hits", s->occlusion_hits}, {"occlusion_batch_loads", s->occlusion_batch_loads},
        {"occlusion_disk_bytes_read", s->occlusion_disk_bytes_read},
        {"peak_rss_bytes", s->peak_rss_bytes},
        {"occlusion_inner_stopped", s->occlusion_inner_stopped},
        {"prototype_loads", s->prototype_loads}, {"decoded_bytes", s->decoded_bytes}};
    const struct { const char *name; double value; } measures[] = {
        {"seconds", s->seconds}, {"load_seconds", s->load_seconds},
        {"build_seconds", s->build_seconds},
        {"bvh_bytes_per_triangle", s->bvh_bytes_per_triangle},
        {"mrays_per_second", s->mrays_per_second}};
    const size_t n_counters = sizeof counters / sizeof counters[0];
    const size_t n_measures = sizeof measures / sizeof measures[0];
    size_t used = 0, i;
    used += (size_t)snprintf(text + used, BRT_STATS_JSON_BYTES - used, "{\n");
    for (i = 0; i < n_counters; i++)
        used += (size_t)snprintf(text + used, BRT_STATS_JSON_BYTES - used, "  \"%s\": %llu,\n",
                                 counters[i].name, (unsigned long long)counters[i].value);
    for (i = 0; i < n_measures; i++) {
        const char *comma = i + 1 < n_measures ? "," : "";
        if (isfinite(measures[i].value))
            used += (size_t)snprintf(text + used, BRT_STATS_JSON_BYTES - used, "  \"%s\": %.17g%s\n",
                                     measures[i].name, measures[i].value, comma);
        else
            used += (size_t)snprintf(text + used, BRT_STATS_JSON_BYTES - used, "  \"%s\": null%s\n",
                                     measures[i].name, comma);
    }
    used += (size_t)snprintf(text + used, BRT_STATS_JSON_BYTES - used, "}\n");
    return used;
}

brt_result brt_stats_write_json(const char *path, const brt_stats *stats, brt_error *err)
{
    char text[BRT_STATS_JSON_BYTES];
    return brt_write_file_atomic(path, text, brt_stats_format_json(stats, text), err);
}

/* ===================================================================== */
/* Results and errors                                                    */
/* ===================================================================== */

const char *brt_result_string(brt_result r)
{
    switch (r) {
    case BRT_OK: return "ok";
    case BRT_ENOMEM: return "out of memory";
    case BRT_EIO: return "i/o error";
    case BRT_EPARSE: return "parse error";
    case BRT_EFORMAT: return "bad scene file";
    case BRT_EARG: return "invalid argument";
    case BRT_ECHECK: return "invariant violated";
    case BRT_EINTR: return "interrupted";
    }
    return "unknown result";
}

brt_result brt_fail(brt_error *err, brt_result r, const char *fmt, ...)
{
    va_list ap;
    if (!err) return r;
    va_start(ap, fmt);
    vsnprintf(err->message, sizeof err->message, fmt, ap);
    va_end(ap);
    return r;
}

/* ===================================================================== */
/* Small utilities                                                       */
/* ===================================================================== */

brt_result brt_parse_size(const char *text, uint64_t *bytes)
{
    uint64_t value = 0, scale = 1;
    const char *p = text;
    if (!text || *p < '0' || *p > '9') return BRT_EARG;
    for (; *p >= '0' && *p <= '9'; p++) {
        if (value > (UINT64_MAX - 9) / 10) return BRT_EARG;
        value = value * 10 + (uint64_t)(*p - '0');
    }
    switch (*p) {
    case 'K': case 'k': scale = (uint64_t)1 << 10; p++; break;
    case 'M': case 'm': scale = (uint64_t)1 << 20; p++; break;
    case 'G': case 'g': scale = (uint64_t)1 << 30; p++; break;
    default: break;
    }
    if (*p == 'B' || *p == 'b') p++;   /* "512MB" reads as 512M */
    if (*p != 0 || value == 0 || value > UINT64_MAX / scale) return BRT_EARG;
    *bytes = value * scale;
    return BRT_OK;
}

/* The one 64-bit mixer of batchrt: SplitMix64's finaliser (Steele, Lea,
** Flood 2014; Stafford's "variant 13" of MurmurHash3's fmix64).  A
** bijection whose outputs for neighbouring inputs look independent: the
** generator below, the DAG's dedup tables (svdag.c) and the renderer's
** counter-based samples (examples/tools/render.c) all use it.  (brt_checksum64
** and bvh.c's vertex_hash are not built on it: their steps are fixed by
** the scene files written.) */
uint64_t brt_mix64(uint64_t z)
{
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

uint64_t brt_random_u64(uint64_t *state)
{
    /* SplitMix64: a Weyl sequence, mixed.  Every seed is a good seed. */
    return brt_mix64(*state += 0x9E3779B97F4A7C15ull);
}

float brt_random_float(uint64_t *state)
{
    /* The top 24 bits give every float in [0,1) with spacing 2^-24. */
    return (float)(brt_random_u64(state) >> 40) * (1.0f / 16777216.0f);
}

/* Little-endian numbers: every file batchrt writes stores them so (scene
** files, the DAG blob, ray and hit records), whatever the host's order.
** Byte by byte, so that neither the host's order nor alignment matters. */
void brt_put_le32(unsigned char *p, uint32_t v)
{
    int i;
    for (i = 0; i < 4; i++) p[i] = (unsigned char)(v >> (8 * i));
}

void brt_put_le64(unsigned char *p, uint64_t v)
{
    brt_put_le32(p, (uint32_t)v);
    brt_put_le32(p + 4, (uint32_t)(v >> 32));
}

uint32_t brt_get_le32(const unsigned char *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

uint64_t brt_get_le64(const unsigned char *p)
{
    return brt_get_le32(p) | (uint64_t)brt_get_le32(p + 4) << 32;
}

/* The one growable array: returns items with room for need elements of
** size bytes (capacity *cap, updated), or NULL with items untouched.
** At least doubling makes n appends cost O(n) copies in total; a first
** need is met exactly (a reservation, as the generated scenes make). */
void *brt_grow(void *items, size_t *cap, size_t need, size_t size)
{
    size_t n = *cap <= SIZE_MAX / 2 ? 2 * *cap : SIZE_MAX;
    void *bigger;
    if (need <= *cap) return items;
    if (n < need) n = need;
    if (n < 16) n = 16;
    if (n > SIZE_MAX / size) return NULL;
    bigger = realloc(items, n * size);
    if (bigger) *cap = n;
    return bigger;
}

double brt_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

uint64_t brt_peak_rss_bytes(void)
{
    struct rusage usage;
    if (getrusage(RUSAGE_SELF, &usage) != 0 || usage.ru_maxrss < 0) return 0;
    return (uint64_t)usage.ru_maxrss * 1024u;   /* Linux and the BSDs: KiB */
}

/* Writes all of data at offset (pwrite), or at the file position when
** offset is negative (write: also pipes and devices).  Short writes and
** EINTR are retried; a write of 0 bytes counts as a full disk. */
int brt_write_fully(int fd, const void *data, size_t size, int64_t offset)
{
    const unsigned char *p = data;
    while (size > 0) {
        ssize_t n = offset < 0 ? write(fd, p, size) : pwrite(fd, p, size, (off_t)offset);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) {
            if (n == 0) errno = ENOSPC;
            return -1;
        }
        p += n;
        size -= (size_t)n;
        if (offset >= 0) offset += n;
    }
    return 0;
}

/* Nonzero when path exists and is not a regular file (a device such as
** /dev/null, a pipe): renaming a file over it would replace it. */
int brt_is_special_file(const char *path)
{
    struct stat st;
    return stat(path, &st) == 0 && !S_ISREG(st.st_mode);
}

/* The one temporary-file-and-rename writer: everything batchrt writes
** (ray, hit and statistics files, scene files, the programs' images, CSV
** and mesh files) is written under "path.tmp.<pid>" and renamed over path
** only when complete, so a failure never leaves a half-written file under
** the final name.
**
** A process that is killed (SIGKILL, the OOM killer, a power loss) cannot
** remove its temporary file, and a scene's can be gigabytes.  So a writer
** holds its temporary file under a POSIX advisory lock (fcntl, a write
** lock on the whole file) from creation to rename; the system releases
** the lock however the process ends.  Before it creates its own, a writer
** removes every "path.tmp.<pid>" that nobody holds (reclaim_stale).  On a
** file system without locks (ENOLCK) nothing is locked and nothing is
** reclaimed, which is safe. */
static int lock_whole_file(int fd)
{
    struct flock lock;
    memset(&lock, 0, sizeof lock);
    lock.l_type = F_WRLCK;
    lock.l_whence = SEEK_SET;   /* l_start = l_len = 0: the whole file, however long */
    return fcntl(fd, F_SETLK, &lock);
}

/* Whether name is base + ".tmp." + a process number other than ours. */
static int is_stale_candidate(const char *name, const char *base, size_t base_len)
{
    const char *digits = name + base_len + 5;
    if (strncmp(name, base, base_len) != 0 || strncmp(name + base_len, ".tmp.", 5) != 0 || !*digits)
        return 0;
    if (strspn(digits, "0123456789") != strlen(digits)) return 0;
    return strtol(digits, NULL, 10) != (long)getpid();
}

/* Removes the temporary files of path that no live writer holds.  Our own
** process number is skipped: probing that file would open and close a
** file we may hold, and closing any descriptor of a file drops this
** process's locks on it (POSIX).  Taking the lock before unlinking means
** a writer that is alive keeps its file. */
static void reclaim_stale(const char *path)
{
    const char *slash = strrchr(path, '/'), *base = slash ? slash + 1 : path;
    char dir[4096], full[4096];
    size_t base_len = strlen(base);
    struct dirent *entry;
    DIR *d;
    if (slash) snprintf(dir, sizeof dir, "%.*s", (int)(slash == path ? 1 : slash - path), path);
    else snprintf(dir, sizeof dir, ".");
    d = opendir(dir);
    if (!d) return;             /* the create below reports what is wrong */
    while ((entry = readdir(d)) != NULL) {
        int fd;
        if (!is_stale_candidate(entry->d_name, base, base_len)) continue;
        if (snprintf(full, sizeof full, "%s/%s", dir, entry->d_name) >= (int)sizeof full) continue;
        fd = open(full, O_RDWR);
        if (fd < 0) continue;
        if (lock_whole_file(fd) == 0) unlink(full);
        close(fd);
    }
    closedir(d);
}

brt_result brt_atomic_open(brt_atomic_file *f, const char *path, brt_error *err)
{
    f->path = path;
    f->fd = -1;
    if (snprintf(f->tmp, sizeof f->tmp, "%s.tmp.%ld", path, (long)getpid()) >= (int)sizeof f->tmp) {
        f->tmp[0] = 0;      /* nothing created: brt_atomic_close has nothing to do */
        return brt_fail(err, BRT_EARG, "%s: path too long", path);
    }
    reclaim_stale(path);
    f->fd = open(f->tmp, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (f->fd < 0) {
        f->tmp[0] = 0;
        return brt_fail(err, BRT_EIO, "%s: cannot create: %s", path, strerror(errno));
    }
    lock_whole_file(f->fd);     /* ENOLCK: unlocked, never reclaimed (above) */
    return BRT_OK;
}

/* The rename comes before the close, so the lock covers the temporary
** file until it has its final name (a close first would leave a moment
** in which another writer's reclaim_stale could take it).  A close that
** fails after the rename (it may have lost data) removes the file again. */
brt_result brt_atomic_close(brt_atomic_file *f, brt_result r, brt_error *err)
{
    int renamed = 0;
    if (f->tmp[0] == 0) return r;
    if (r == BRT_OK && rename(f->tmp, f->path) != 0)
        r = brt_fail(err, BRT_EIO, "%s: cannot rename: %s", f->path, strerror(errno));
    renamed = r == BRT_OK;
    if (f->fd >= 0 && close(f->fd) != 0 && r == BRT_OK)   /* a failed close may lose data */
        r = brt_fail(err, BRT_EIO, "%s: cannot write: %s", f->path, strerror(errno));
    f->fd = -1;
    if (r != BRT_OK) unlink(renamed ? f->path : f->tmp);
    f->tmp[0] = 0;
    return r;
}

brt_result brt_write_file_atomic(const char *path, const void *data,
                                 size_t size, brt_error *err)
{
    brt_atomic_file f;
    brt_result r;
    if (brt_is_special_file(path)) {
        int fd = open(path, O_WRONLY), failed;
        failed = fd < 0 || brt_write_fully(fd, data, size, -1) != 0;
        if (fd >= 0 && close(fd) != 0) failed = 1;
        return failed ? brt_fail(err, BRT_EIO, "%s: cannot write: %s", path, strerror(errno)) : BRT_OK;
    }
    r = brt_atomic_open(&f, path, err);
    if (r == BRT_OK && brt_write_fully(f.fd, data, size, 0) != 0)
        r = brt_fail(err, BRT_EIO, "%s: cannot write: %s", path, strerror(errno ? errno : EIO));
    return brt_atomic_close(&f, r, err);
}

/* ===================================================================== */
/* Threads: a small pool and a split of the work                         */
/* ===================================================================== */
/*
** A pool runs one job at a time on its threads, the caller being thread 0.
** A job hands out [0, total) in chunks from one counter; every output is
** written per item (a hit, a ray's slot, a batching point's buffers) or
** summed per thread, so which thread took which chunk changes no byte.
** The pool lives as long as one trace or one build: the library keeps no
** global state (only the tests' copy has some: testing.h's hooks).  With
** one thread no thread is created and the job runs in the caller, as the
** code read before threads.
*/

unsigned brt_threads_resolve(unsigned threads)
{
    /* _SC_NPROCESSORS_ONLN is not in POSIX, but glibc, musl, the BSDs
    ** and macOS all have it; elsewhere one thread. */
#ifdef _SC_NPROCESSORS_ONLN
    long online = sysconf(_SC_NPROCESSORS_ONLN);
#else
    long online = 1;
#endif
    if (threads == 0) threads = online > 0 ? (unsigned)online : 1u;
    return threads < BRT_MAX_THREADS ? threads : BRT_MAX_THREADS;
}

/* Takes the next chunk of the current job (lock held); 0: none left. */
static int pool_take(brt_pool *p, size_t *first, size_t *end)
{
    if (p->next >= p->total) return 0;
    *first = p->next;
    *end = p->total - p->next < p->chunk ? p->total : p->next + p->chunk;
    p->next = *end;
    return 1;
}

/* Runs one chunk (lock held on entry and return) and marks it done. */
static void pool_chunk(brt_pool *p, unsigned thread, size_t first, size_t end)
{
    pthread_mutex_unlock(&p->lock);
    p->job(p->ctx, thread, first, end);
    pthread_mutex_lock(&p->lock);
    p->done[first / p->chunk] = 1;
    pthread_cond_signal(&p->progress);
}

/* The caller's part of a job: it commits the chunks in order as they are
** done, and runs chunks itself while the next one to commit is not. */
static void pool_commit_in_order(brt_pool *p, brt_pool_commit commit)
{
    size_t chunks = (p->total + p->chunk - 1) / p->chunk, c = 0, first, end;
    pthread_mutex_lock(&p->lock);
    while (c < chunks) {
        if (p->done[c]) {
            pthread_mutex_unlock(&p->lock);
            end = (c + 1) * p->chunk < p->total ? (c + 1) * p->chunk : p->total;
            if (commit) commit(p->ctx, c * p->chunk, end);
            c++;
            pthread_mutex_lock(&p->lock);
        } else if (pool_take(p, &first, &end)) {
            pool_chunk(p, 0, first, end);
        } else {
            pthread_cond_wait(&p->progress, &p->lock);
        }
    }
    while (p->busy > 0) pthread_cond_wait(&p->idle, &p->lock);
    pthread_mutex_unlock(&p->lock);
}

typedef struct pool_thread {
    brt_pool *p;
    unsigned index;
} pool_thread;

static void *pool_main(void *arg)
{
    brt_pool *p = ((pool_thread *)arg)->p;
    unsigned index = ((pool_thread *)arg)->index;
    unsigned long seen = 0;
    size_t first, end;
    free(arg);
    pthread_mutex_lock(&p->lock);
    for (;;) {
        while (p->round == seen && !p->quit) pthread_cond_wait(&p->wake, &p->lock);
        if (p->quit) break;
        seen = p->round;
        while (pool_take(p, &first, &end)) pool_chunk(p, index, first, end);
        if (--p->busy == 0) pthread_cond_signal(&p->idle);
    }
    pthread_mutex_unlock(&p->lock);
    return NULL;
}

/* Starts up to threads - 1 threads; fewer when the system refuses (the
** results do not depend on the count). */
void brt_pool_init(brt_pool *p, unsigned threads)
{
    memset(p, 0, sizeof *p);
    p->count = 1;
    threads = brt_threads_resolve(threads);
    if (threads < 2) return;
    pthread_mutex_init(&p->lock, NULL);
    pthread_cond_init(&p->wake, NULL);
    pthread_cond_init(&p->idle, NULL);
    pthread_cond_init(&p->progress, NULL);
    p->threads = malloc((threads - 1) * sizeof *p->threads);
    while (p->threads && p->count < threads) {
        pool_thread *arg = malloc(sizeof *arg);
        if (!arg) break;
        arg->p = p;
        arg->index = p->count;
        if (pthread_create(&p->threads[p->count - 1], NULL, pool_main, arg) != 0) {
            free(arg);
            break;
        }
        p->count++;
    }
}

void brt_pool_free(brt_pool *p)
{
    unsigned i;
    if (!p->threads) return;
    pthread_mutex_lock(&p->lock);
    p->quit = 1;
    pthread_cond_broadcast(&p->wake);
    pthread_mutex_unlock(&p->lock);
    for (i = 0; i + 1 < p->count; i++) pthread_join(p->threads[i], NULL);
    free(p->threads);
    free(p->done);
    pthread_mutex_destroy(&p->lock);
    pthread_cond_destroy(&p->wake);
    pthread_cond_destroy(&p->idle);
    pthread_cond_destroy(&p->progress);
}

/* Runs job over [0, total) in chunks of at most chunk items, on every
** thread of the pool, and, when commit is not NULL, commit over the same
** chunks in order, in the calling thread, each as soon as it and those
** before it are done (so one thread's serial work overlaps the others'
** jobs).  Returns when all is done.  Below two chunks, or without room
** for the chunk flags, the caller runs it alone. */
void brt_pool_run(brt_pool *p, brt_pool_job job, brt_pool_commit commit, void *ctx, size_t total,
                     size_t chunk)
{
    size_t chunks = (total + chunk - 1) / chunk;
    if (total == 0) return;
    if (chunks > p->done_cap && p->count > 1 && chunks > 1) {
        unsigned char *done = realloc(p->done, chunks);
        if (done) {
            p->done = done;
            p->done_cap = chunks;
        }
    }
    if (p->count < 2 || chunks < 2 || chunks > p->done_cap) {
        job(ctx, 0, 0, total);
        if (commit) commit(ctx, 0, total);
        return;
    }
    memset(p->done, 0, chunks);
    pthread_mutex_lock(&p->lock);
    p->job = job;
    p->ctx = ctx;
    p->next = 0;
    p->total = total;
    p->chunk = chunk;
    p->busy = p->count - 1;
    p->round++;
    pthread_cond_broadcast(&p->wake);
    pthread_mutex_unlock(&p->lock);
    pool_commit_in_order(p, commit);
}

