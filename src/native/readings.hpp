// sensors.SensorStream._read in C++: one row's new readings from its new ticks' measurements, in one pass (stride,
// latency, bias, noise), each number as the Python specification makes it, bit for bit: reading n of a sensor is
// ((z + bias) + noise · draw) component by component, z its measurement `latency` readings before (the first one
// before that), the draws from the sensor's own stream (noise.hpp) in reading order then component order.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <vector>

#include "noise.hpp"

namespace multibody_sim
{
  // One sensor as SensorStream reads it (SensorStream.native_data()'s items)
  struct ReadingItem
  {
    int offset = 0;   // its first component in a tick's row
    int width = 0;    // its components
    int stride = 1;   // it reads every `stride` ticks (those whose count since the row's start is a multiple)
    int latency = 0;  // readings late
    int history = 0;  // where its last `latency` measurements (latency × width) start in a row's history
    bool spoiled = false;        // it draws noise (any component's noise is not zero)
    std::vector<double> bias;    // (width,)
    std::vector<double> noise;   // (width,) standard deviations
  };

  // A run's sensors as SensorStream reads them (SensorStream.native_data())
  struct ReadingLayout
  {
    int width = 0;    // components in a tick's row
    int history = 0;  // numbers in a row's history
    std::vector<ReadingItem> items;
    ZigguratTables tables;
  };

  // How many of m ticks, the first `count` ticks after the row's start, a sensor reading every `stride` reads at
  inline int64_t due_ticks(int64_t count, std::size_t m, int stride)
  {
    const int64_t s = stride, first = (s - count % s) % s, n = static_cast<int64_t>(m);
    return first < n ? (n - first + s - 1) / s : 0;
  }

  // The numbers the strided sensors read at m ticks, the first `count` ticks after the row's start
  inline std::size_t strided_readings(const ReadingLayout & layout, int64_t count, std::size_t m)
  {
    std::size_t n = 0;
    for (const ReadingItem & p : layout.items)
      if (p.stride != 1)
        n += static_cast<std::size_t>(due_ticks(count, m, p.stride) * p.width);
    return n;
  }

  // The readings of one row's m new ticks, measurements Z (m, width), the first at `count` ticks since the row's
  // start: the sensors that read at every tick into their columns of out (m, width; it may be Z, or overlap it), each
  // other sensor's readings into `apart` after the previous ones' (its n due ticks: n × width), with the others'
  // columns of out the measurements plus the bias (as the specification leaves them). Updates the row's latest
  // readings (width,), its history (the ring of each late sensor's last measurements: reading n's in slot
  // n % latency, all the first one's before it) and its streams' states (one per sensor, 4 words each).
  inline void make_readings(const ReadingLayout & layout, const double * Z, std::size_t m, double * out, double * apart,
                            int64_t count, double * latest, double * history, uint64_t * states)
  {
    const auto & items = layout.items;
    const std::size_t numbers = m * static_cast<std::size_t>(layout.width);
    std::vector<double> measured;  // Z, when out overlaps it from another row (its rows would be written before read)
    if (Z != out && Z < out + numbers && out < Z + numbers)
    {
      measured.assign(Z, Z + numbers);
      Z = measured.data();
    }
    std::vector<double *> to(items.size(), nullptr);  // each strided sensor's next reading in `apart`
    double * next = apart;
    for (std::size_t k = 0; k < items.size(); ++k)
      if (items[k].stride != 1)
      {
        to[k] = next;
        next += due_ticks(count, m, items[k].stride) * items[k].width;
      }
    std::vector<double> z(layout.width), delayed(layout.width);  // a tick's measurements (out may be Z); a late one
    for (std::size_t i = 0; i < m; ++i)
    {
      const int64_t tick = count + static_cast<int64_t>(i);
      const double * row = Z + i * layout.width;
      double * written = out + i * layout.width;
      std::copy(row, row + layout.width, z.begin());
      for (std::size_t k = 0; k < items.size(); ++k)
      {
        const ReadingItem & p = items[k];
        const double * zk = z.data() + p.offset;
        double * target = written + p.offset;
        if (p.stride != 1)
        {
          for (int j = 0; j < p.width; ++j)
            target[j] = zk[j] + p.bias[j];
          if (tick % p.stride != 0)
            continue;
          target = to[k];
          to[k] += p.width;
        }
        if (p.latency)
        {
          const int64_t n = tick / p.stride;  // readings before this one
          double * ring = history + p.history;
          if (n == 0)
            for (int l = 0; l < p.latency; ++l)
              std::copy(zk, zk + p.width, ring + l * p.width);
          double * slot = ring + (n % p.latency) * p.width;
          for (int j = 0; j < p.width; ++j)
          {
            delayed[j] = slot[j];
            slot[j] = zk[j];
          }
          zk = delayed.data();
        }
        for (int j = 0; j < p.width; ++j)
          target[j] = zk[j] + p.bias[j];
        if (p.spoiled)
        {
          Sfc64 bits{states + 4 * k};
          for (int j = 0; j < p.width; ++j)
          {
            const double noise = standard_normal(bits, layout.tables) * p.noise[j];
            target[j] = target[j] + noise;
          }
        }
        std::copy(target, target + p.width, latest + p.offset);
      }
    }
  }

  // The layout's own checks (its sizes agree), for its binding
  inline void check_readings(const ReadingLayout & layout)
  {
    int history = 0;
    for (const ReadingItem & p : layout.items)
    {
      if (p.width < 0 || p.offset < 0 || p.offset + p.width > layout.width)
        throw std::invalid_argument("ReadingItem: offset and width must lie within the layout's width");
      if (p.stride < 1 || p.latency < 0)
        throw std::invalid_argument("ReadingItem: stride must be at least 1, latency at least 0");
      if (static_cast<int>(p.bias.size()) != p.width || static_cast<int>(p.noise.size()) != p.width)
        throw std::invalid_argument("ReadingItem: bias and noise need one entry per component (width)");
      if (p.history != history)
        throw std::invalid_argument("ReadingItem.history must follow the previous late sensors' (latency x width)");
      history += p.latency * p.width;
    }
    if (history != layout.history)
      throw std::invalid_argument("ReadingLayout.history must be the sum of latency x width over the items");
    if (layout.tables.width.size() != 256)
      throw std::invalid_argument("ReadingLayout.tables: the noise's ZigguratTables");
  }
} // namespace multibody_sim
