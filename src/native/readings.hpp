// readings.SensorStream._read_python in C++: one row's new readings from its new ticks' measurements, in one pass
// (stride, latency, bias, noise), each number as the Python specification makes it, bit for bit: reading n of a
// sensor is ((z + bias) + noise · draw) component by component, z its measurement `latency` readings before (the
// first one before that), the draws from the sensor's own stream (noise.hpp) in reading order then component order.
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

  // The numbers the strided sensors read at m ticks, the first `count` ticks after the row's start (a sensor reads
  // at the ticks whose count is a multiple of its stride)
  inline std::size_t strided_readings(const ReadingLayout & layout, int64_t count, std::size_t m)
  {
    std::size_t n = 0;
    for (const ReadingItem & p : layout.items)
      if (p.stride != 1)
      {
        const int64_t s = p.stride, first = (s - count % s) % s, ticks = static_cast<int64_t>(m);
        n += static_cast<std::size_t>(first < ticks ? (ticks - first + s - 1) / s * p.width : 0);
      }
    return n;
  }

  // The readings of one row's m new ticks, measurements Z (m, width), the first at `count` ticks since the row's
  // start: the sensors that read at every tick into their columns of out (m, width; it may be Z, or overlap it), each
  // other sensor's readings into `apart` after the previous ones' (its n due ticks: n × width), with the others'
  // columns of out the measurements plus the bias (as the specification leaves them). Sensor by sensor, tick by
  // tick: each sensor's draws come from its own stream, in reading then component order, as the specification's.
  // Updates the row's latest readings (width,), its history (the ring of each late sensor's last measurements:
  // reading n's in slot n % latency, all the first one's before it) and its streams' states (one per sensor, 4 words
  // each).
  inline void make_readings(const ReadingLayout & layout, const double * Z, std::size_t m, double * out, double * apart,
                            int64_t count, double * latest, double * history, uint64_t * states)
  {
    const std::size_t w = static_cast<std::size_t>(layout.width), numbers = m * w;
    std::vector<double> measured;  // Z, when out overlaps it from another row (its rows would be written before read)
    if (Z != out && Z < out + numbers && out < Z + numbers)
    {
      measured.assign(Z, Z + numbers);
      Z = measured.data();
    }
    std::vector<double> delayed(w);  // a late sensor's measurement
    double * to = apart;             // the strided sensors' next reading
    for (std::size_t k = 0; k < layout.items.size(); ++k)  // sensor by sensor (each one's draws in their order)
    {
      const ReadingItem & p = layout.items[k];
      const double *bias = p.bias.data(), *noise = p.noise.data();
      uint64_t * state = states + 4 * k;
      uint64_t words[4] = {state[0], state[1], state[2], state[3]};  // (kept in registers, written back once)
      Sfc64 bits{words};
      const double * last = nullptr;  // its latest reading
      // (counted along, without a division per tick:) ticks since its last reading, its readings so far, and the
      // ring's slot of the next reading's measurement (reading n's in slot n % latency)
      int64_t since = count % p.stride;
      int64_t n = (count + p.stride - 1) / p.stride;
      int64_t slot = p.latency ? n % p.latency : 0;
      for (std::size_t i = 0; i < m; ++i)
      {
        const double * zk = Z + i * w + p.offset;
        double * written = out + i * w + p.offset;  // (zk itself when out is Z: each number read before written)
        const bool due = since == 0;
        if (++since == p.stride)
          since = 0;
        if (due)
        {
          double * target = written;
          if (p.stride != 1)
          {
            target = to;
            to += p.width;
          }
          const double * z = zk;
          if (p.latency)
          {
            double * ring = history + p.history;
            if (n == 0)  // its first reading: the first measurement stands for those before it
              for (int l = 0; l < p.latency; ++l)
                std::copy(zk, zk + p.width, ring + l * p.width);
            double * held = ring + slot * p.width;
            for (int j = 0; j < p.width; ++j)
            {
              delayed[j] = held[j];
              held[j] = zk[j];
            }
            z = delayed.data();
            if (++slot == p.latency)
              slot = 0;
          }
          ++n;
          for (int j = 0; j < p.width; ++j)
            target[j] = z[j] + bias[j];
          if (p.spoiled)
            for (int j = 0; j < p.width; ++j)
            {
              const double spoil = standard_normal(bits, layout.tables) * noise[j];
              target[j] = target[j] + spoil;
            }
          last = target;
        }
        if (p.stride != 1)  // its columns of out: the measurement plus the bias, as the specification leaves them
          for (int j = 0; j < p.width; ++j)
            written[j] = zk[j] + bias[j];
      }
      std::copy(words, words + 4, state);
      if (last != nullptr)
        std::copy(last, last + p.width, latest + p.offset);
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
