/* Taker: rcl_take of one subscription into a kept C message (see module.c). */
#include "fastpath.h"

/* A gid as rclpy 9 gives it in message info: {"implementation_identifier", "data"}. */
PyObject * gid_dict(const rmw_gid_t * gid)
{
  return Py_BuildValue(
    "{s:s,s:y#}", "implementation_identifier", gid->implementation_identifier, "data",
    (const char *)gid->data, (Py_ssize_t)RMW_GID_STORAGE_SIZE);
}

void * capsule_of(PyObject * type, const char * name)
{
  void * pointer;
  PyObject * capsule = PyObject_GetAttrString(type, name);
  if (capsule == NULL) {
    return NULL;
  }
  pointer = PyCapsule_GetPointer(capsule, NULL);
  Py_DECREF(capsule);
  return pointer;
}

static int Taker_init(TakerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"subscription", "message_type", "publisher_gid", NULL};
  unsigned long long subscription;
  PyObject * type;
  create_message_t create;
  int with_gid = 0;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "KO|$p", keywords, &subscription, &type, &with_gid)) {
    return -1;
  }
  self->with_gid = with_gid;
  if (subscription == 0 || self->message != NULL) {
    PyErr_SetString(PyExc_ValueError, "Taker needs an rcl subscription's address, once");
    return -1;
  }
  create = (create_message_t)capsule_of(type, "_CREATE_ROS_MESSAGE");
  if (create == NULL) {
    return -1;
  }
  self->destroy = (destroy_message_t)capsule_of(type, "_DESTROY_ROS_MESSAGE");
  if (self->destroy == NULL) {
    return -1;
  }
  self->to_py = (convert_to_py_t)capsule_of(type, "_CONVERT_TO_PY");
  if (self->to_py == NULL) {
    return -1;
  }
  self->message = create();
  if (self->message == NULL) {
    PyErr_NoMemory();
    return -1;
  }
  self->subscription = (const rcl_subscription_t *)(uintptr_t)subscription;
  return 0;
}

static void Taker_dealloc(TakerObject * self)
{
  if (self->message != NULL) {
    self->destroy(self->message);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * sequence_or_none(uint64_t value)
{
  if (value == RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED) {
    Py_RETURN_NONE;
  }
  return PyLong_FromUnsignedLongLong(value);
}

/* One message: None when there is none, else the message, or with info
 * (message, info) with rclpy's keys. */
PyObject * taker_take(TakerObject * self, int with_info)
{
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  rcl_ret_t ret;
  PyObject * message;
  PyObject * dict;
  if (self->message == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Taker not initialised");
    return NULL;
  }
  ret = rcl_take(self->subscription, self->message, &info, NULL);
  if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take");
  }
  message = self->to_py(self->message);
  if (message == NULL || !with_info) {
    return message;
  }
  dict = Py_BuildValue(
    "{s:L,s:L,s:N,s:N}",
    "source_timestamp", (long long)info.source_timestamp,
    "received_timestamp", (long long)info.received_timestamp,
    "publication_sequence_number", sequence_or_none(info.publication_sequence_number),
    "reception_sequence_number", sequence_or_none(info.reception_sequence_number));
  if (dict != NULL && self->with_gid) {
    PyObject * gid = gid_dict(&info.publisher_gid);
    if (gid == NULL || PyDict_SetItemString(dict, "publisher_gid", gid) < 0) {
      Py_CLEAR(dict);
    }
    Py_XDECREF(gid);
  }
  if (dict == NULL) {
    Py_DECREF(message);
    return NULL;
  }
  return Py_BuildValue("(NN)", message, dict);
}

static PyObject * Taker_take(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return taker_take(self, 0);
}

static PyObject * Taker_take_with_info(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return taker_take(self, 1);
}

static PyMethodDef Taker_methods[] = {
  {"take", (PyCFunction)Taker_take, METH_NOARGS, "take() -> message | None"},
  {"take_with_info", (PyCFunction)Taker_take_with_info, METH_NOARGS,
   "take_with_info() -> (message, info) | None, info as rclpy's take_message gives it"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject TakerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Taker",
  .tp_doc = "rcl_take of one subscription, converted with its message type's capsules.",
  .tp_basicsize = sizeof(TakerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Taker_init,
  .tp_dealloc = (destructor)Taker_dealloc,
  .tp_methods = Taker_methods,
};

