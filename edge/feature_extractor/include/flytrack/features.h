/* libflytrack_features: camera frames -> 2D feature points (seed 000 §2, flydra/Braid style).
 *
 * Per pixel: a running Gaussian average of the background (mean and mean of squares, updated every
 * `bg_update_interval` frames with weight `alpha`). A pixel is a candidate when its difference to
 * the background mean exceeds both `diff_threshold` and `n_sigma` x the background std. Candidates
 * are grouped into 8-connected regions; each region gives one point: peak difference beta, pixels
 * below max(`clear_fraction` x beta, `diff_threshold`, `despeckle_threshold`) cleared, area (pixel
 * count), centre (1st moments), orientation and eccentricity (2nd central moments), then the centre
 * is corrected for lens distortion (OpenCV model, as the host's camera.py). Points are ordered
 * strongest first.
 *
 * No allocation after ft_fx_create; one object per camera, not thread-safe (one thread per camera).
 * Pixel (0, 0) is the centre of the top-left pixel, as in OpenCV and camera.py.
 */
#ifndef FLYTRACK_FEATURES_H
#define FLYTRACK_FEATURES_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define FT_FX_ABI_VERSION 1

/* The most points a frame may return (max_points): a FEATURES datagram carries 32 points and a
 * frame splits over at most 255 parts (protocol/SPEC.md), so more could not be sent. */
#define FT_FX_MAX_POINTS 8160u

/* Pixel formats; the numbers are the STATUS message's (SPEC §1.2). MONO16 is host-endian uint16. */
enum { FT_FX_MONO8 = 0, FT_FX_MONO16 = 1, FT_FX_YUYV = 2 };

/* Which differences count: absolute, only brighter than the background, only darker. */
enum { FT_FX_POLARITY_BOTH = 0, FT_FX_POLARITY_BRIGHT = 1, FT_FX_POLARITY_DARK = 2 };

/* Result codes (0 is success; negatives are errors). */
enum {
    FT_FX_OK = 0,
    FT_FX_E_ARG = -1,           /* NULL pointer or invalid argument */
    FT_FX_E_SIZE = -2,          /* width/height/stride out of range */
    FT_FX_E_FORMAT = -3,        /* unknown pixel format */
    FT_FX_E_NOMEM = -4,         /* allocation failed at create */
    FT_FX_E_FRAME_SIZE = -5,    /* frame buffer smaller than the geometry requires */
    FT_FX_E_UNKNOWN_PARAM = -6, /* ft_fx_set_param: no such parameter */
    FT_FX_E_BAD_VALUE = -7,     /* parameter value out of range or not finite */
    FT_FX_E_ABI = -8            /* the caller's struct sizes differ from the library's */
};

/* Flags in ft_fx_result.flags. */
#define FT_FX_RES_BACKGROUND_TAKEN 0x1u /* this frame became the background; no points */
#define FT_FX_RES_BG_UPDATED 0x2u       /* the running background was updated after this frame */
#define FT_FX_RES_CAND_OVERFLOW                                                                    \
    0x4u                         /* more candidate pixels than max_candidates: the rest ignored */
#define FT_FX_RES_TRUNCATED 0x8u /* more regions than max_points: only the strongest kept */

typedef struct {
    uint32_t width, height;
    uint32_t stride;             /* bytes between rows; 0 = packed (width x bytes per pixel) */
    int32_t pixel_format;        /* FT_FX_MONO8, FT_FX_MONO16, FT_FX_YUYV (luma used) */
    int32_t polarity;            /* FT_FX_POLARITY_* */
    double alpha;                /* background running-average weight, (0, 1]; Braid 0.01 */
    double n_sigma;              /* std multiple a candidate must exceed; Braid 7 */
    double diff_threshold;       /* absolute difference a candidate must exceed; Braid 30 */
    uint32_t bg_update_interval; /* update the background every N frames (0 = never); Braid 200 */
    double clear_fraction; /* pixels below this fraction of the region's peak are cleared; 0.3 */
    double despeckle_threshold; /* pixels with a difference below this are cleared too (Braid 5) */
    uint32_t min_area;          /* regions with fewer kept pixels are dropped as speckle; 1 */
    int32_t subtract_cut;    /* 1: moment weight = diff - cut (weights fall to 0 at the edge: less
                                centre bias); 0: weight = diff, as flydra */
    uint32_t max_points;     /* at most this many per frame, strongest first; 1..FT_FX_MAX_POINTS */
    uint32_t max_candidates; /* candidate pixels examined per frame; 0 = 65536 */
    /* Camera calibration for undistortion (camera.py: K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]],
     * dist = k1 k2 p1 p2 k3). fx = 0 means no calibration: undistorted = distorted. */
    double fx, fy, cx, cy, skew;
    double k1, k2, p1, p2, k3;
} ft_fx_params;

typedef struct {
    double x_dist, y_dist;     /* centre in the (distorted) image, px */
    double x_undist, y_undist; /* after lens-distortion correction, px */
    double area;               /* kept pixels of the region */
    double peak_diff;          /* beta: the region's largest difference to the background */
    double orientation;        /* major axis angle from +x, (-pi/2, pi/2]; NaN when round */
    double eccentricity;       /* major / minor axis ratio >= 1; NaN when undefined (a line) */
    double mean_val;           /* background running mean at the peak */
    double sumsq_val;          /* background running mean of squares at the peak */
    uint32_t cur_val;          /* pixel value at the peak */
    uint32_t peak_x, peak_y;   /* the peak pixel */
    uint32_t n_candidates;     /* candidate pixels in the region */
} ft_fx_point;

typedef struct {
    uint64_t frame_index;      /* frames fed so far, this one included */
    uint32_t n_points;         /* points returned (<= max_points) */
    uint32_t total_points;     /* regions found (before max_points) */
    uint32_t n_candidates;     /* candidate pixels seen */
    uint32_t flags;            /* FT_FX_RES_* */
    const ft_fx_point *points; /* n_points points, valid until the next call on this extractor */
} ft_fx_result;

typedef struct ft_fx ft_fx;

/* Braid's defaults for a frame of the given geometry. */
void ft_fx_params_default(ft_fx_params *p, uint32_t width, uint32_t height, int32_t pixel_format);

/* Checks the parameters; FT_FX_OK or the first problem (msg, if not NULL, gets a sentence). */
int ft_fx_params_check(const ft_fx_params *p, char *msg, size_t msg_len);

/* Creates an extractor (all memory allocated here). params_size = sizeof(ft_fx_params) guards the
 * ABI for foreign callers (ctypes). */
int ft_fx_create(const ft_fx_params *p, size_t params_size, ft_fx **out);
void ft_fx_destroy(ft_fx *fx);

/* Bytes one frame must have with these parameters. */
size_t ft_fx_frame_bytes(const ft_fx_params *p);

/* Feeds one frame (nbytes >= ft_fx_frame_bytes). The first frame, and the first after
 * ft_fx_take_background, becomes the background and yields no points. */
int ft_fx_process(ft_fx *fx, const void *frame, size_t nbytes, ft_fx_result *res);

/* The next frame replaces the background (mean = frame, variance 0). */
void ft_fx_take_background(ft_fx *fx);

/* Mask: width x height bytes, nonzero = use the pixel. NULL removes the mask. */
int ft_fx_set_mask(ft_fx *fx, const uint8_t *mask);

/* Runtime parameters by name (CONTROL SET_PARAM): alpha, n_sigma, diff_threshold,
 * bg_update_interval, polarity, clear_fraction, despeckle_threshold, min_area, subtract_cut,
 * max_points. Geometry and calibration are fixed at create. */
int ft_fx_set_param(ft_fx *fx, const char *name, double value);
int ft_fx_get_param(const ft_fx *fx, const char *name, double *value);
const ft_fx_params *ft_fx_get_params(const ft_fx *fx);

/* The background model (width x height floats, row-major, packed); NULL before the first frame. */
const float *ft_fx_background_mean(const ft_fx *fx);
const float *ft_fx_background_sumsq(const ft_fx *fx);

/* Lens-distortion correction of one point with the calibration in p (camera.py Camera.undistort).
 */
void ft_fx_undistort(const ft_fx_params *p, double u, double v, double *u_out, double *v_out);

const char *ft_fx_strerror(int code);
int ft_fx_abi_version(void);
size_t ft_fx_sizeof_params(void);
size_t ft_fx_sizeof_point(void);

#ifdef __cplusplus
}
#endif
#endif /* FLYTRACK_FEATURES_H */
