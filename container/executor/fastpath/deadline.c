/* Deadline: the process ends with a given status at a given moment, unless cancelled first.
 *
 * For a wait that Python cannot bound itself: code that holds the GIL and
 * never returns (a pybind11 destructor deep in rcl and Fast DDS: the DDS
 * participant's destruction deadlocked once in 32 runs of the signals test)
 * leaves every other Python thread unable to run, a join's timeout included.
 * This thread never touches Python: at the moment it says one line through
 * rcutils' console sink (rclpy's own output handler takes the GIL, which is
 * the thing held), flushes C's streams and calls _exit with the status.
 *
 * Ownership: the thread borrows the object, which never outlives it:
 * cancel() and the object's collection join the thread first.
 */
#include "fastpath.h"

#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <unistd.h>

#include <rcutils/logging.h>
#include <rcutils/time.h>

typedef struct {
  PyObject_HEAD
  pthread_mutex_t lock;
  pthread_cond_t cond; /* on CLOCK_MONOTONIC */
  struct timespec at;  /* when the process ends (CLOCK_MONOTONIC) */
  int code;
  int cancelled;       /* under lock */
  int running;         /* the thread was started and not joined (only with the GIL) */
  char * logger;       /* owned copies, freed after the join */
  char * message;
  pthread_t thread;
} DeadlineObject;

static void console(const char * logger, const char * format, ...)
{
  rcutils_log_location_t location = {"Deadline", __FILE__, __LINE__};
  rcutils_time_point_value_t now = 0;
  va_list args;
  if (rcutils_system_time_now(&now) != RCUTILS_RET_OK) {
    now = 0;
  }
  va_start(args, format);
  rcutils_logging_console_output_handler(&location, RCUTILS_LOG_SEVERITY_WARN, logger, now, format, &args);
  va_end(args);
}

static void * wait_then_end(void * arg)
{
  DeadlineObject * self = (DeadlineObject *)arg;
  pthread_mutex_lock(&self->lock);
  while (!self->cancelled) {
    if (pthread_cond_timedwait(&self->cond, &self->lock, &self->at) == ETIMEDOUT) {
      break;
    }
  }
  if (self->cancelled) {
    pthread_mutex_unlock(&self->lock);
    return NULL;
  }
  pthread_mutex_unlock(&self->lock);
  console(self->logger, "%s", self->message);
  fflush(NULL);
  _exit(self->code);
}

static char * copy_of(PyObject * text)
{
  Py_ssize_t size;
  const char * utf8 = PyUnicode_AsUTF8AndSize(text, &size);
  char * copy;
  if (utf8 == NULL) {
    return NULL;
  }
  copy = malloc((size_t)size + 1);
  if (copy == NULL) {
    PyErr_NoMemory();
    return NULL;
  }
  memcpy(copy, utf8, (size_t)size + 1);
  return copy;
}

static PyObject * Deadline_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  DeadlineObject * self = (DeadlineObject *)type->tp_alloc(type, 0);
  pthread_condattr_t attributes;
  (void)args;
  (void)kwargs;
  if (self == NULL) {
    return NULL;
  }
  pthread_mutex_init(&self->lock, NULL);
  pthread_condattr_init(&attributes);
  pthread_condattr_setclock(&attributes, CLOCK_MONOTONIC);
  pthread_cond_init(&self->cond, &attributes);
  pthread_condattr_destroy(&attributes);
  self->cancelled = 0;
  self->running = 0;
  self->logger = NULL;
  self->message = NULL;
  return (PyObject *)self;
}

static int Deadline_init(DeadlineObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"seconds", "code", "logger", "message", NULL};
  double seconds;
  int code;
  PyObject * logger;
  PyObject * message;
  long long at;
  int error;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "d$iUU", keywords, &seconds, &code, &logger, &message)) {
    return -1;
  }
  if (self->running || self->logger != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Deadline is initialised once");
    return -1;
  }
  if (!(seconds >= 0.0) || seconds > 1e9) {
    PyErr_SetString(PyExc_ValueError, "Deadline: seconds from 0 to 1e9");
    return -1;
  }
  self->logger = copy_of(logger);
  self->message = self->logger == NULL ? NULL : copy_of(message);
  if (self->message == NULL) {
    return -1;
  }
  self->code = code;
  at = monotonic_ns() + (long long)(seconds * 1e9);
  self->at.tv_sec = (time_t)(at / 1000000000LL);
  self->at.tv_nsec = (long)(at % 1000000000LL);
  error = pthread_create(&self->thread, NULL, wait_then_end, self);
  if (error != 0) {
    errno = error;
    PyErr_SetFromErrno(PyExc_OSError);
    return -1;
  }
  self->running = 1;
  return 0;
}

static void deadline_cancel(DeadlineObject * self)
{
  if (!self->running) {
    return;
  }
  self->running = 0;
  pthread_mutex_lock(&self->lock);
  self->cancelled = 1;
  pthread_cond_signal(&self->cond);
  pthread_mutex_unlock(&self->lock);
  Py_BEGIN_ALLOW_THREADS
  pthread_join(self->thread, NULL);
  Py_END_ALLOW_THREADS
}

static PyObject * Deadline_cancel(DeadlineObject * self, PyObject * Py_UNUSED(ignored))
{
  deadline_cancel(self);
  Py_RETURN_NONE;
}

static void Deadline_dealloc(DeadlineObject * self)
{
  deadline_cancel(self);
  free(self->logger);
  free(self->message);
  pthread_cond_destroy(&self->cond);
  pthread_mutex_destroy(&self->lock);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMethodDef Deadline_methods[] = {
  {"cancel", (PyCFunction)Deadline_cancel, METH_NOARGS,
   "cancel() -> None: the process does not end (the thread is joined); again, nothing"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject DeadlineType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Deadline",
  .tp_doc = "Deadline(seconds, *, code, logger, message): unless cancelled within seconds, a thread that "
            "never touches Python says message (WARN, under logger, on rcutils' console sink) and ends "
            "the process with status code",
  .tp_basicsize = sizeof(DeadlineObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = Deadline_new,
  .tp_init = (initproc)Deadline_init,
  .tp_dealloc = (destructor)Deadline_dealloc,
  .tp_methods = Deadline_methods,
};
