/* FlyTrack wire protocol: common definitions (protocol/SPEC.md).
 *
 * Error codes shared by every decoder, their SPEC names, byte-wise little-endian load/store helpers
 * and fixed-size text helpers. Header-only C99, no allocation, no float; compiles with avr-gcc.
 */
#ifndef FLYTRACK_WIRE_H
#define FLYTRACK_WIRE_H

#include <stddef.h>
#include <stdint.h>

#define FT_PROTOCOL_VERSION 2

/* Decoder and encoder results. The names (ft_err_name) are the SPEC's, shared with the Python codec
 * and the golden vectors; FT_E_NO_SPACE is the encoders' "output buffer too small". */
typedef enum {
    FT_OK = 0,
    FT_E_TRUNCATED,
    FT_E_BAD_MAGIC,
    FT_E_BAD_VERSION,
    FT_E_UNKNOWN_TYPE,
    FT_E_LENGTH_MISMATCH,
    FT_E_COUNT_OVERFLOW,
    FT_E_NOT_FINITE,
    FT_E_BAD_FIELD,
    FT_E_BAD_COBS,
    FT_E_BAD_CRC,
    FT_E_NO_SPACE
} ft_err;

static inline const char *ft_err_name(ft_err e) {
    switch (e) {
    case FT_OK:
        return "OK";
    case FT_E_TRUNCATED:
        return "TRUNCATED";
    case FT_E_BAD_MAGIC:
        return "BAD_MAGIC";
    case FT_E_BAD_VERSION:
        return "BAD_VERSION";
    case FT_E_UNKNOWN_TYPE:
        return "UNKNOWN_TYPE";
    case FT_E_LENGTH_MISMATCH:
        return "LENGTH_MISMATCH";
    case FT_E_COUNT_OVERFLOW:
        return "COUNT_OVERFLOW";
    case FT_E_NOT_FINITE:
        return "NOT_FINITE";
    case FT_E_BAD_FIELD:
        return "BAD_FIELD";
    case FT_E_BAD_COBS:
        return "BAD_COBS";
    case FT_E_BAD_CRC:
        return "BAD_CRC";
    case FT_E_NO_SPACE:
        return "NO_SPACE";
    }
    return "UNKNOWN_ERROR";
}

/* Little-endian loads and stores, one byte at a time: alignment and host byte order never matter.
 */
static inline uint16_t ft_ld_u16(const uint8_t *p) {
    return (uint16_t)((uint16_t)p[0] | (uint16_t)((uint16_t)p[1] << 8));
}
static inline uint32_t ft_ld_u32(const uint8_t *p) {
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}
static inline uint64_t ft_ld_u64(const uint8_t *p) {
    return (uint64_t)ft_ld_u32(p) | ((uint64_t)ft_ld_u32(p + 4) << 32);
}
/* Two's complement without relying on implementation-defined unsigned -> signed conversion. */
static inline int64_t ft_ld_i64(const uint8_t *p) {
    uint64_t u = ft_ld_u64(p);
    if (u <= (uint64_t)INT64_MAX)
        return (int64_t)u;
    return -(int64_t)(~u) - 1;
}
static inline void ft_st_u16(uint8_t *p, uint16_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
}
static inline void ft_st_u32(uint8_t *p, uint32_t v) {
    p[0] = (uint8_t)v;
    p[1] = (uint8_t)(v >> 8);
    p[2] = (uint8_t)(v >> 16);
    p[3] = (uint8_t)(v >> 24);
}
static inline void ft_st_u64(uint8_t *p, uint64_t v) {
    ft_st_u32(p, (uint32_t)v);
    ft_st_u32(p + 4, (uint32_t)(v >> 32));
}
static inline void ft_st_i64(uint8_t *p, int64_t v) {
    ft_st_u64(p, (uint64_t)v);
}

/* Fixed-size text fields (SPEC: NUL-padded UTF-8; a text filling the field has no NUL; bytes after
 * the first NUL must be NUL). In structs a field of n bytes is held as char[n + 1], NUL-terminated.
 * UTF-8 validity is not checked (the SPEC names no error for it); bytes are carried as they are. */

/* FT_E_BAD_FIELD if a non-NUL byte follows the first NUL. */
static inline ft_err ft_text_check(const uint8_t *p, size_t n) {
    size_t i = 0;
    while (i < n && p[i] != 0)
        i++;
    for (; i < n; i++)
        if (p[i] != 0)
            return FT_E_BAD_FIELD;
    return FT_OK;
}

/* Copies a checked field of n bytes into dst (n + 1 bytes), NUL-terminated. */
static inline void ft_text_load(char *dst, const uint8_t *p, size_t n) {
    size_t i;
    for (i = 0; i < n; i++)
        dst[i] = (char)p[i];
    dst[n] = 0;
}

/* Whether src (char[n + 1]) holds a NUL within its n + 1 bytes, i.e. fits a field of n bytes. */
static inline int ft_text_fits(const char *src, size_t n) {
    size_t i;
    for (i = 0; i <= n; i++)
        if (src[i] == 0)
            return 1;
    return 0;
}

/* Writes src (char[n + 1]) into a field of n bytes, NUL-padded. FT_E_BAD_FIELD if src has no NUL
 * within its n + 1 bytes (the text does not fit). */
static inline ft_err ft_text_store(uint8_t *p, size_t n, const char *src) {
    size_t len = 0, i;
    while (len < n && src[len] != 0)
        len++;
    if (len == n && src[n] != 0)
        return FT_E_BAD_FIELD;
    for (i = 0; i < n; i++)
        p[i] = i < len ? (uint8_t)src[i] : 0;
    return FT_OK;
}

#endif /* FLYTRACK_WIRE_H */
