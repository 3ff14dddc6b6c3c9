// Backward-pass kernels of the trainer. Internal to trainer/.
#pragma once

#include <cstddef>
#include <cstdint>

namespace lsnif::trainer::detail {

// dWt[i][o] += sum_r X[r*ldx + i] * G[r*outp + o] for i < in, o < outp (outp multiple
// of 16). The weight-gradient GEMM (X^T G) in the layout the forward kernel reads.
// With `live_rows` (in values), rows r >= live_rows[i] hold X[r][i] == 0 and are skipped for
// input i (per block of inputs, up to the block's largest): each element then adds its
// rows' products in the same order, less terms that are exact zeros (which could only change
// the sign of a zero sum).
void outer_accumulate(const float* X, std::size_t n, std::size_t in, std::size_t ldx, const float* G,
                      std::size_t outp, float* dWt, const std::uint32_t* live_rows = nullptr);

}  // namespace lsnif::trainer::detail
