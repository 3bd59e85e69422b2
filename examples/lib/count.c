/*
** count.c -- the triangles of a mesh file counted before it is read, for
** the default size of a batching point (ex_default_point_tris): an OBJ in
** one scan of its bytes, a PLY from its header.  input.c and pbrt.c (a
** plymesh) use it; the fuzz targets link it with pbrt.c.
*/
#include "count.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* A PLY header's "element face N", read line by line up to end_header. */
static uint64_t ply_faces(FILE *f)
{
    char *line = NULL;
    size_t cap = 0;
    unsigned long long n;
    uint64_t faces = 0;
    while (getline(&line, &cap, f) > 0 && strncmp(line, "end_header", 10) != 0)
        if (sscanf(line, "element face %llu", &n) == 1) faces = n;
    free(line);
    return faces;
}

static int blank(int c) { return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f'; }

/* An OBJ's triangles: on each line whose first word is "f", its corners
** before a '#' less two.  Other lines are skipped to their newline. */
static uint64_t obj_triangles(FILE *f)
{
    enum { START, KEYWORD, FACE, SKIP } state = START;
    static char buf[1 << 16];
    uint64_t triangles = 0, corners = 0;
    size_t n, i;
    int in_corner = 0;
    while ((n = fread(buf, 1, sizeof buf, f)) > 0) {
        for (i = 0; i < n; i++) {
            int c = (unsigned char)buf[i];
            if (state == SKIP) {
                const char *nl = memchr(buf + i, '\n', n - i);
                if (!nl) break;
                i = (size_t)(nl - buf);
                c = '\n';
            }
            if (c == '\n') {
                if (state == FACE && corners + in_corner >= 3) triangles += corners + in_corner - 2;
                state = START, corners = 0, in_corner = 0;
            } else if (state == START) {
                if (c == 'f') state = KEYWORD;
                else if (!blank(c)) state = SKIP;
            } else if (state == KEYWORD) {
                state = blank(c) ? FACE : SKIP;
            } else if (state == FACE) {
                if (c == '#') {   /* a comment ends the face */
                    if (corners + in_corner >= 3) triangles += corners + in_corner - 2;
                    state = SKIP, corners = 0, in_corner = 0;
                } else if (blank(c)) {
                    corners += in_corner;
                    in_corner = 0;
                } else {
                    in_corner = 1;
                }
            }
        }
    }
    if (state == FACE && corners + in_corner >= 3) triangles += corners + in_corner - 2;
    return triangles;
}

uint64_t ex_mesh_file_triangles(const char *path)
{
    FILE *f = fopen(path, "rb");
    char magic[5] = {0};
    uint64_t triangles;
    if (!f) return 0;
    /* "ply" on a line of its own, as brt_mesh_load tells the formats apart */
    if (fread(magic, 1, 5, f) >= 4 && memcmp(magic, "ply", 3) == 0 &&
        (magic[3] == '\n' || (magic[3] == '\r' && magic[4] == '\n')))
        triangles = ply_faces(f);
    else {
        rewind(f);
        triangles = obj_triangles(f);
    }
    fclose(f);
    return triangles;
}
