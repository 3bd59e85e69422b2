/*
** batchrt.c -- everything of batchrt that is neither a BVH nor a voxel proxy:
** results and errors, small utilities, mesh loading (OBJ, PLY), ray and hit
** files, statistics, and (later) the out-of-core batched traversal of
** Pharr et al. 1997 with the proxies of Molenaar and Eisemann 2020.
*/
#include "batchrt.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

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

uint64_t brt_random_u64(uint64_t *state)
{
    /* SplitMix64 (Steele, Lea, Flood 2014): every seed is a good seed. */
    uint64_t z = (*state += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
}

float brt_random_float(uint64_t *state)
{
    /* The top 24 bits give every float in [0,1) with spacing 2^-24. */
    return (float)(brt_random_u64(state) >> 40) * (1.0f / 16777216.0f);
}

double brt_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

brt_result brt_write_file_atomic(const char *path, const void *data,
                                 size_t size, brt_error *err)
{
    char tmp[4096];
    const unsigned char *p = data;
    int fd, saved;
    if (snprintf(tmp, sizeof tmp, "%s.tmp.%ld", path, (long)getpid()) >= (int)sizeof tmp)
        return brt_fail(err, BRT_EARG, "%s: path too long", path);
    fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd < 0)
        return brt_fail(err, BRT_EIO, "%s: cannot create: %s", path, strerror(errno));
    while (size > 0) {
        ssize_t n = write(fd, p, size);
        if (n < 0 && errno == EINTR) continue;
        if (n <= 0) goto fail;
        p += n;
        size -= (size_t)n;
    }
    if (close(fd) != 0) { fd = -1; goto fail; }
    if (rename(tmp, path) != 0) { fd = -1; goto fail; }
    return BRT_OK;
fail:
    saved = errno;
    if (fd >= 0) close(fd);
    unlink(tmp);
    return brt_fail(err, BRT_EIO, "%s: cannot write: %s", path, strerror(saved ? saved : EIO));
}

/* ===================================================================== */
/* Rays and hits                                                         */
/* ===================================================================== */

void brt_hit_clear(brt_hit *hit)
{
    hit->t = INFINITY;
    hit->prim = BRT_NO_PRIM;
    hit->u = hit->v = 0.0f;
}

int brt_hit_is_closer(float t, uint32_t prim, const brt_hit *current)
{
    return t < current->t || (t == current->t && prim < current->prim);
}
